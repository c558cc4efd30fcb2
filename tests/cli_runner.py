"""Run `rtwalk ARGS` for a test: in this process by default, or as a real `python -m viewer.cli`
child (`subprocess=True`) where the process boundary is what is tested (signals, resource limits,
environment the libraries read at load time, warnings, the exit status the shell sees).

A child costs ~0.8 s of imports before it parses a flag; most CLI tests check a one-line error that
comes before any work, so in-process runs make them ~50x cheaper. The in-process run reproduces
what the interpreter does with `sys.exit(main())`: stdout/stderr captured, SystemExit -> its code
(argparse: 2 with usage), any other escaping exception -> 1 with the traceback on stderr (so
"no Traceback in stderr" keeps its meaning), Python warnings printed to stderr with the
interpreter's default filters. Process-wide state the commands touch is put back after each run:
os.environ, cwd, SIGINT/SIGTERM handlers, NumPy error state, root logging handlers, moderngl's
default context and the current OpenGL context (each command's own EGL context is released)."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import signal
import subprocess as sp
import sys
import traceback
import warnings
from collections.abc import Iterator

_WARNINGS_IGNORED_BY_DEFAULT = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def run_cli(*args: str, timeout: float = 180, subprocess: bool = False, **popen) -> sp.CompletedProcess:
    """`rtwalk ARGS` -> CompletedProcess(returncode, stdout, stderr). `timeout` and `popen`
    (env=, cwd=, preexec_fn=) apply to the child only (`subprocess=True`)."""
    if subprocess:
        return sp.run([sys.executable, "-m", "viewer.cli", *args], capture_output=True, text=True,
                      timeout=timeout, **popen)
    assert not popen, f"{sorted(popen)} need a child process: pass subprocess=True"
    return run_in_process(list(args))


def run_in_process(argv: list[str]) -> sp.CompletedProcess:
    from viewer.cli import main

    out, err = io.StringIO(), io.StringIO()
    with _restored_process_state(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            _interpreter_warnings():
        try:
            code = _exit_status(main(argv))
        except SystemExit as exc:
            code = _exit_status(exc.code, err)
        except BaseException:  # what the interpreter prints for an uncaught exception, exit 1
            traceback.print_exc(file=err)
            code = 1
    return sp.CompletedProcess(["rtwalk", *argv], code, out.getvalue(), err.getvalue())


def _exit_status(code, err: io.StringIO | None = None) -> int:
    """sys.exit(code) semantics: None -> 0, int -> itself, anything else printed, 1."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    if err is not None:
        print(code, file=err)
    return 1


@contextlib.contextmanager
def _interpreter_warnings() -> Iterator[None]:
    """Warnings reach the captured stderr as a fresh interpreter would show them (pytest would
    otherwise record them in its summary; changing the filters also resets "once" registries)."""
    with warnings.catch_warnings():
        warnings.resetwarnings()
        warnings.simplefilter("default")
        for category in _WARNINGS_IGNORED_BY_DEFAULT:
            warnings.simplefilter("ignore", category)

        def show(message, category, filename, lineno, file=None, line=None) -> None:
            sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))

        warnings.showwarning = show
        yield


@contextlib.contextmanager
def _restored_process_state() -> Iterator[None]:
    import moderngl
    import numpy as np

    import viewer.gl.context as glc

    environ, cwd = dict(os.environ), os.getcwd()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    np_err = np.geterr()
    root = logging.getLogger()
    log_handlers, log_level = list(root.handlers), root.level
    default_gl = moderngl._store.default_context
    create, created = glc.create_headless_context, []

    def tracked_context():
        ctx = create()
        created.append(ctx)
        return ctx

    glc.create_headless_context = tracked_context  # the commands import it at call time
    try:
        yield
    finally:
        glc.create_headless_context = create
        for ctx in created:
            if ctx is not glc._CTX:  # the shared context made inside the command (its first use) stays
                ctx.release()
        moderngl._store.default_context = default_gl
        if created and glc._CTX is not None:
            glc._CTX.__enter__()  # a new context became current at creation: the shared one is again
        root.handlers[:], root.level = log_handlers, log_level
        np.seterr(**np_err)
        for s, h in handlers.items():
            signal.signal(s, h)
        os.chdir(cwd)
        if dict(os.environ) != environ:
            os.environ.clear()
            os.environ.update(environ)
