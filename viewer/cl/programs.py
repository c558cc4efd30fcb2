"""Kernel sources (.cl files in the package) with `#include "file"` expansion, and a program cache.

`#include "name"` is expanded in Python from a search path: the including file's folder, then
viewer/cl/kernels (so backend folders can include the shared headers). Each file is included
once per program (include guards are not needed). The cache key is (expanded source, defines,
device), so an edited .cl file or another define builds a new program; PoCL keeps the binaries
across runs in POCL_CACHE_DIR (see context.ensure_pocl_cache_dir).

One numeric contract on every device (docs/numerics.md): every program's source starts with
NUMERIC_PRELUDE (`#pragma OPENCL FP_CONTRACT OFF`: no a*b+c fused into an FMA, which NVIDIA does
by default and PoCL does not), and is built with `-cl-fp32-correctly-rounded-divide-sqrt` where the
device offers it (OpenCL allows 2.5 ulp for float `/` otherwise) and never with a fast-math option,
so a kernel gives the bits of IEEE float32 evaluated operation by operation, as NumPy does.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from viewer.cl.context import ClContext, cl_context
from viewer.errors import RtwalkError

KERNELS_DIR = Path(__file__).resolve().parent / "kernels"
_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*$', re.M)

NUMERIC_PRELUDE = "#pragma OPENCL FP_CONTRACT OFF\n"
CORRECT_DIV_SQRT = "-cl-fp32-correctly-rounded-divide-sqrt"
# options that would let the compiler trade the contract for speed: never passed (tests check)
FORBIDDEN_OPTIONS = ("-cl-mad-enable", "-cl-fast-relaxed-math", "-cl-unsafe-math-optimizations",
                     "-cl-finite-math-only", "-cl-no-signed-zeros", "-cl-denorms-are-zero")

_cache: dict[tuple[str, tuple[tuple[str, str], ...], int], Any] = {}


def resolve(path: str | Path, search: Iterable[Path] = ()) -> Path:
    """A kernel file: an absolute path as given, else looked up in `search` then KERNELS_DIR (never in
    the working directory: a stray file there must not replace a packaged kernel)."""
    p = Path(path)
    if p.is_absolute():
        return p.resolve()
    for d in (*search, KERNELS_DIR):
        cand = Path(d) / p
        if cand.is_file():
            return cand.resolve()
    where = ", ".join(map(str, (*search, KERNELS_DIR)))
    raise RtwalkError(f"OpenCL kernel file {str(path)!r} not found (searched {where})")


def expand(path: str | Path, search: Iterable[Path] = ()) -> str:
    """The source of a .cl file with every `#include "x"` replaced by x's (expanded) text."""
    seen: set[Path] = set()

    def load(p: Path) -> str:
        if p in seen:
            return f"/* {p.name}: already included */\n"
        seen.add(p)
        text = p.read_text()

        def sub(m: re.Match) -> str:
            inc = resolve_from(m.group(1), p.parent)
            return f"/* begin {inc.name} */\n{load(inc)}\n/* end {inc.name} */"

        return _INCLUDE.sub(sub, text)

    def resolve_from(name: str, folder: Path) -> Path:
        for d in (folder, *search, KERNELS_DIR):
            cand = Path(d) / name
            if cand.is_file():
                return cand.resolve()
        raise RtwalkError(f"OpenCL kernel include {name!r} not found (from {folder})")

    return load(resolve(path, search))


def _options(defines: Mapping[str, Any] | None) -> tuple[tuple[str, str], ...]:
    return tuple(sorted((str(k), "" if v is None else str(v)) for k, v in (defines or {}).items()))


def program_source(path: str | Path, search: Iterable[Path] = (), prelude: str = "") -> str:
    """The exact text `build` compiles: NUMERIC_PRELUDE first (so no kernel can forget it), then
    `prelude`, then the expanded file."""
    return NUMERIC_PRELUDE + (prelude + "\n" if prelude else "") + expand(path, search)


def build_options(defines: Mapping[str, Any] | None, ctx: ClContext) -> list[str]:
    """-D options for `defines` plus the numeric-contract options for ctx's device."""
    args = [f"-D{k}={v}" if v != "" else f"-D{k}" for k, v in _options(defines)]
    if int(ctx.device.single_fp_config) & int(ctx.cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT):
        args.append(CORRECT_DIV_SQRT)
    return args


def build(path: str | Path, defines: Mapping[str, Any] | None = None, ctx: ClContext | None = None,
          search: Iterable[Path] = (), prelude: str = "") -> Any:
    """The built pyopencl.Program for a kernel file and defines ({"WG": 64, "FAST": None} ->
    -D WG=64 -D FAST), cached per (expanded source, defines, device). `prelude` is source text put
    before the file (for macros with spaces or parentheses, e.g. a predicate)."""
    ctx = ctx or cl_context()
    src = program_source(path, search, prelude)
    opts = _options(defines)
    key = (src, opts, int(ctx.device.int_ptr))
    prog = _cache.get(key)
    if prog is None:
        args = build_options(defines, ctx)
        try:
            prog = ctx.cl.Program(ctx.context, src).build(options=args)
        except ctx.cl.Error as e:  # RuntimeError (build log) or LogicError (bad options, invalid program)
            first = str(e).strip().splitlines()
            raise RtwalkError(f"OpenCL build of {Path(path).name} failed: {' | '.join(first[:8])}") from None
        _cache[key] = prog
    return prog


def warm_up(specs: Iterable[tuple[str | Path, Mapping[str, Any] | None]], ctx: ClContext | None = None) -> float:
    """Build each (path, defines) and create its kernels ahead of the first frame; returns ms.

    PoCL also compiles a work-group function per local size at the first enqueue: run each kernel
    once at its fixed size too (the primitives' `warm_up()` does) to take that out of frame 1."""
    t0 = time.perf_counter()
    for path, defines in specs:
        build(path, defines, ctx).all_kernels()
    return (time.perf_counter() - t0) * 1e3


def clear_cache() -> None:
    _cache.clear()
