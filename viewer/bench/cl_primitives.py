"""`rtwalk bench-cl`: OpenCL primitive throughput next to NumPy on the same data, in one run.

For each size: stable key-value sort (OpenCL radix sort vs np.argsort(kind="stable") plus the
gather of keys, i.e. both produce sorted keys and their original indices), exclusive scan (vs
np.cumsum) and stream compaction of half the elements (vs boolean indexing). Data are random
uint32 (full 32-bit keys, 4 sort passes). The OpenCL inputs live on the device before timing (as
in a backend); each time runs from enqueue to queue finish. Repetitions interleave NumPy and
OpenCL (alternating which goes first); medians and the median of per-repetition ratios are
reported. Writes bench_cl.json, bench_cl.md and bench_cl.png to --out.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from viewer.bench.common import add_count_option, parse_counts
from viewer.bench.harness import load_average
from viewer.bench.partial import keep_partial, mark_complete, write_plots
from viewer.bench.plots import bars, figure, finish
from viewer.bench.report import md_table, write_study
from viewer.cl import io as clio
from viewer.cli_args import check_output_dir, check_report_free
from viewer.errors import RtwalkError

HELP = "OpenCL sort/scan/compact throughput next to NumPy"
OPS = ("sort", "scan", "compact")
NUMPY_NAMES = {"sort": 'np.argsort(kind="stable") + gather', "scan": "np.cumsum", "compact": "a[mask]"}


def parse_sizes(text: str) -> list[int]:
    """"1M,10M" -> [1000000, 10000000] (suffixes K, M; plain integers too)."""
    return parse_counts(text, "--elements")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_count_option(parser, "--elements", "1M,10M", "element counts")
    parser.add_argument("--reps", type=int, default=7, help="interleaved repetitions per measurement (default 7)")
    parser.add_argument("--ops", default=",".join(OPS), help="subset of sort,scan,compact (default all)")
    parser.add_argument("--out", default="out/bench-cl", help="output folder (default %(default)s)")


def _time(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


class _Case:
    """One op at one size: a NumPy callable and an OpenCL callable (which finishes the queue),
    plus a `prepare` run before each OpenCL repetition, outside the timing."""

    def __init__(self, op: str, n: int, prims, rng: np.random.Generator):
        ctx = prims.ctx
        cl, q = ctx.cl, ctx.queue
        mf = cl.mem_flags
        self.op, self.n = op, n
        self.prepare: Callable[[], None] = ctx.finish

        def dev(a: np.ndarray):
            return clio.upload(ctx, a, mf.READ_WRITE)

        if op == "sort":
            keys = rng.integers(0, 2**32, n, dtype=np.uint32)
            idx = np.arange(n, dtype=np.uint32)
            k0, v0, kb, vb = dev(keys), dev(idx), dev(keys), dev(idx)

            def np_sort():
                order = np.argsort(keys, kind="stable")
                return keys[order], order

            def prep():
                clio.copy(q, kb, k0)
                clio.copy(q, vb, v0)
                ctx.finish()

            def cl_sort():
                prims.sort_pairs(kb, vb, n, key_bits=32)
                ctx.finish()

            self.numpy, self.opencl, self.prepare = np_sort, cl_sort, prep
            self._check = lambda: self._check_sort(ctx, keys, kb, vb)
        elif op == "scan":
            a = rng.integers(0, 1000, n, dtype=np.uint32)
            ab, ob = dev(a), dev(np.empty_like(a))
            self.numpy = lambda: np.cumsum(a, dtype=np.uint32)

            def cl_scan():
                prims.exclusive_scan(ab, ob, n)
                ctx.finish()

            self.opencl = cl_scan
            self._check = lambda: self._check_scan(ctx, a, ob)
        else:
            a = rng.integers(0, 2**32, n, dtype=np.uint32)
            mask = rng.random(n) < 0.5
            ab, fb, ob = dev(a), dev(mask.astype(np.uint32)), dev(np.empty_like(a))
            self.numpy = lambda: a[mask]
            self.opencl = lambda: prims.compact(n, flags=fb, src=ab, dst=ob)  # reads the count: finished
            self._check = lambda: self._check_compact(ctx, a, mask, ob, self.opencl())

    @staticmethod
    def _check_sort(ctx, keys, kb, vb) -> None:
        k, v = np.empty_like(keys), np.empty_like(keys)
        clio.copy(ctx.queue, k, kb)
        clio.copy(ctx.queue, v, vb)
        eq = k[1:] == k[:-1]
        if not ((k[1:] >= k[:-1]).all() and (keys[v] == k).all() and (v[1:][eq] > v[:-1][eq]).all()):
            raise RuntimeError("OpenCL sort result is wrong")

    @staticmethod
    def _check_scan(ctx, a, ob) -> None:
        o = np.empty_like(a)
        clio.copy(ctx.queue, o, ob)
        if not (o[0] == 0 and (o[1:] == np.cumsum(a, dtype=np.uint32)[:-1]).all()):
            raise RuntimeError("OpenCL scan result is wrong")

    @staticmethod
    def _check_compact(ctx, a, mask, ob, m) -> None:
        o = np.empty(m, np.uint32)
        clio.copy(ctx.queue, o, ob)
        if m != mask.sum() or not (o == a[mask]).all():
            raise RuntimeError("OpenCL compaction result is wrong")

    def check(self) -> None:
        """Run once (warm-up) and verify the OpenCL result against NumPy."""
        self.prepare()
        self.opencl()
        self._check()


def measure(sizes: list[int], ops: list[str], reps: int, command: str = "", log=print,
            keep: Callable[[dict], None] | None = None, check: Callable[[], None] | None = None) -> dict:
    """The report; `keep` gets it before the first row (an interrupted run writes the rows so far)
    and `check` runs between (op, size) rows (a deferred Ctrl-C stops there: viewer.bench.partial)."""
    from viewer.cl.context import cl_context
    from viewer.cl.primitives import primitives

    ctx = cl_context()
    prims = primitives(ctx)
    t0 = time.perf_counter()
    prims.warm_up()
    warm_ms = (time.perf_counter() - t0) * 1e3
    rng = np.random.default_rng(2024)
    rows: list[dict] = []
    report = {"device": ctx.name, "compute_units": ctx.compute_units, "host": platform.node(),
              "cpu_count": os.cpu_count(), "load_average_before": load_average(), "reps": reps,
              "warm_up_ms": warm_ms, "command": command, "rows": rows}
    if keep is not None:
        keep(report)
    for n in sizes:
        for op in ops:
            if check is not None:
                check()
            case = _Case(op, n, prims, rng)
            case.check()
            case.numpy()
            np_ms, cl_ms = [], []
            for r in range(reps):
                case.prepare()
                if r % 2:
                    cl_ms.append(_time(case.opencl))
                    np_ms.append(_time(case.numpy))
                else:
                    np_ms.append(_time(case.numpy))
                    case.prepare()
                    cl_ms.append(_time(case.opencl))
            ratio = float(np.median(np.array(np_ms) / np.array(cl_ms)))
            row = {"op": op, "n": n, "numpy": NUMPY_NAMES[op], "numpy_ms": float(np.median(np_ms)),
                   "opencl_ms": float(np.median(cl_ms)), "speedup": ratio, "numpy_samples_ms": np_ms,
                   "opencl_samples_ms": cl_ms}
            row["numpy_melem_s"] = n / row["numpy_ms"] / 1e3
            row["opencl_melem_s"] = n / row["opencl_ms"] / 1e3
            rows.append(row)
            log(f"{op:8s} n={n:>11,d}  numpy {row['numpy_ms']:9.2f} ms  opencl {row['opencl_ms']:8.2f} ms  "
                f"speedup {ratio:6.1f}x")
            del case
    return report


def markdown(report: dict) -> str:
    rows = [[r["op"], f"{r['n']:,}", r["numpy"], f"{r['numpy_ms']:.2f}", f"{r['opencl_ms']:.2f}",
             f"{r['numpy_melem_s']:.1f}", f"{r['opencl_melem_s']:.1f}", f"{r['speedup']:.1f}x"] for r in report["rows"]]
    table = md_table(["op", "elements", "NumPy", "NumPy ms", "OpenCL ms", "NumPy Melem/s", "OpenCL Melem/s",
                      "speedup"], rows, align="lrlrrrrr")
    return "\n".join([f"OpenCL primitives vs NumPy on {report['device']} ({report['compute_units']} compute units), "
                      f"median of {report['reps']} interleaved repetitions; speedup = median of per-repetition "
                      "NumPy/OpenCL ratios.", "", table, "", f"Command: `{report['command']}`", ""])


def plot(report: dict, path: Path) -> None:
    rows = report["rows"]
    fig, ax = figure(size=(max(6.0, 1.1 * len(rows) + 2), 4.2))
    bars(ax, [f"{r['op']}\n{r['n'] / 1e6:g}M" for r in rows],
         {"NumPy": [r["numpy_melem_s"] for r in rows], "OpenCL": [r["opencl_melem_s"] for r in rows]},
         ylabel="million elements / s (log)", log=True, texts=[f"{r['speedup']:.1f}x" for r in rows],
         texts_of="OpenCL", title=f"OpenCL primitives vs NumPy: {report['device']}")
    finish(fig, path)


def run(args: argparse.Namespace) -> int:
    sizes = parse_sizes(args.elements)
    ops = [o.strip() for o in args.ops.split(",") if o.strip()]
    bad = [o for o in ops if o not in OPS]
    if bad or not ops:
        raise RtwalkError(f"bad --ops '{args.ops}': choose from {','.join(OPS)}")
    if args.reps < 1:
        raise RtwalkError("--reps must be >= 1")
    out = check_output_dir(args.out, "--out")
    check_report_free([out / "bench_cl.json"], getattr(args, "force", False))
    def write(report: dict, complete: bool) -> dict:
        files = write_study(out, "bench_cl", mark_complete(report, complete), markdown(report))
        write_plots(lambda: plot(report, files["png"]))  # after the JSON: a plot failure never loses it
        return files

    held: list[dict] = []
    with keep_partial("bench-cl", defer=True) as part:  # Ctrl-C: stop after the row in hand, keep the rows
        part.keep(lambda complete: write(held[0], complete)["json"] if held and held[0]["rows"] else None)
        report = measure(sizes, ops, args.reps, getattr(args, "command_line", ""), keep=held.append,
                         check=part.check)
    files = write(report, True)
    print()
    print(files["markdown"])
    print(f"wrote {files['json']}, {files['md']}, {files['png']}")
    return 0
