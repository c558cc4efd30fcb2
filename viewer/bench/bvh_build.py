"""`rtwalk bench-bvh`: build time, M triangles/s and SAH cost of each BVH builder on the city.

bvh-build.json is {"complete", "command", "rows"} (complete false: interrupted, the builds finished
so far; viewer.bench.partial). One row per (size, builder): BuildStats.to_dict() plus `builder`, `target`
(the asked size), `build_time_s`, `throughput_mtris_per_s`, `sah_cost`, `sah_ratio` (to the
SAH build of the same size when it ran), `bvh4_time_s` (host collapse to BVH4, build_bvh4),
`bvh4_device_time_s` (the same on the OpenCL device, viewer.accel.bvh4_device, when it has fp64) and, for
the device builder, `phases_s` and `iterations` (PLOC); `io`: the build's launches, host syncs and
bytes (viewer.iostats); `cpu_time_s` (the process's user + system time during the build, PoCL's
threads included) and `load_average` (1-minute, at the start of the build). The device builder is
warmed up on a small city first (kernel compilation is not build time, nor is it in the build time
a render reports); each size's first device build still pays for first-touching its buffers, as a
render's build does. So a row times what a user's build costs: the same call, the same phases.

Why the CPU time: on the shared 2-core machine the wall time of the same build swings 2x with the
other users' load (a 10 M build: 1.4 s with both cores free, 2.6-3.4 s with one taken, at the same
CPU time), which made a bench run look slower than the build inside a render measured at a quieter
moment; the CPU time and the load say which case a row is.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from viewer.bench.common import add_count_option
from viewer.bench.partial import keep_partial
from viewer.cli_args import check_output_dir, check_report_free, parse_choices, parse_sizes

BUILDERS = ("sah", "device")


HELP = "BVH build time, throughput and SAH cost per builder on the city scene"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_count_option(p, "--triangles", "1000000,5000000",
                     "city triangle counts to build (each as --scene-size accepts)")
    p.add_argument("--builders", default="sah",
                   help="comma list of builders: sah (CPU binned SAH), device (OpenCL Morton + PLOC), or all")
    p.add_argument("--seed", type=int, default=1, help="seed of the procedural city")
    p.add_argument("--out", default="out/bench", help="folder for bvh-build.json")


def _build(builder: str, tris):
    if builder == "device":
        from viewer.accel.bvh_device import build_bvh_device

        return build_bvh_device(tris)
    from viewer.accel.bvh import build_bvh

    return build_bvh(tris)


def _device_bvh4() -> bool:
    """Whether the device BVH4 collapse is timed too (OpenCL with float64); its kernels compiled."""
    from viewer.cl import cl_available

    if cl_available() is not None:
        return False
    from viewer.accel.bvh import build_bvh
    from viewer.accel.bvh4_device import build_bvh4_device, device_supported
    from viewer.cl import cl_context
    from viewer.procedural import make_city

    if not device_supported(cl_context()):
        return False
    build_bvh4_device(build_bvh(make_city(2000, 1).triangles))
    return True


def run(args) -> int:
    from viewer.bench.report import write_json
    from viewer.procedural import make_city
    from viewer.scene_io import check_seed

    sizes = parse_sizes(args.triangles, flag="--triangles")
    check_seed(args.seed)
    builders = parse_choices(args.builders, BUILDERS, "--builders")
    out = check_output_dir(args.out, "--out")
    check_report_free([out / "bvh-build.json"], getattr(args, "force", False))
    if "device" in builders:
        from viewer.cl import cl_available
        from viewer.errors import RtwalkError

        reason = cl_available()
        if reason is not None:
            raise RtwalkError(f"--builders device needs an OpenCL device: {reason}")
        _build("device", make_city(2000, args.seed).triangles)  # compile and warm the kernels
    device4 = _device_bvh4()
    rows: list[dict] = []
    path = out / "bvh-build.json"

    def write(complete: bool) -> Path | None:
        if not rows and not complete:
            return None
        write_json(path, {"complete": complete, "command": getattr(args, "command_line", ""), "rows": rows})
        return path

    with keep_partial("bench-bvh", defer=True) as part:  # Ctrl-C: stop after the build in hand, keep the rows
        part.keep(write)
        _measure(sizes, builders, device4, args.seed, rows, part)
    write(True)
    print(f"report: {path}")
    return 0


def _measure(sizes: list[int], builders: list[str], device4: bool, seed: int, rows: list[dict], part) -> None:
    """Append one row per (size, builder) to `rows`; `part.check()` between builds (Ctrl-C)."""
    from viewer import iostats
    from viewer.accel.bvh4 import build_bvh4
    from viewer.procedural import make_city

    for n in sizes:
        scene = make_city(n, seed)
        sah_cost = None
        for builder in builders:
            part.check()
            load = os.getloadavg()[0]
            iostats.begin_frame()
            c0 = time.process_time()
            bvh = _build(builder, scene.triangles)
            cpu = time.process_time() - c0
            io = iostats.end_frame()
            t0 = time.perf_counter()
            build_bvh4(bvh)
            r = bvh.stats.to_dict()
            r["bvh4_time_s"] = time.perf_counter() - t0
            if device4:
                from viewer.accel.bvh4_device import build_bvh4_device

                t0 = time.perf_counter()
                build_bvh4_device(bvh)
                r["bvh4_device_time_s"] = time.perf_counter() - t0
            r["builder"] = builder
            r["cpu_time_s"] = cpu
            r["load_average"] = load
            r["io"] = io.as_dict()  # launches, host syncs and bytes of the build (device builder)
            r["target"] = n
            mtris = bvh.stats.triangles / max(bvh.stats.build_time_s, 1e-9) / 1e6
            r["throughput_mtris_per_s"] = r["mtris_per_s"] = mtris
            if builder == "device":
                from viewer.accel.bvh_device import device_builder

                b = device_builder()
                r["phases_s"] = dict(b.phases)
                r["iterations"] = b.iterations
            if builder == "sah":
                sah_cost = r["sah_cost"]
            r["sah_ratio"] = r["sah_cost"] / sah_cost if sah_cost else None
            rows.append(r)
            ratio = f", {r['sah_ratio']:.3f}x sah" if r["sah_ratio"] is not None and builder != "sah" else ""
            print(f"city {scene.triangle_count:>10,} tris {builder:>6}: build {r['build_time_s']:.2f} s "
                  f"({r['throughput_mtris_per_s']:.2f} Mtri/s; CPU {cpu:.2f} s, load {load:.1f}), "
                  f"{r['nodes']:,} nodes, depth {r['depth']}, "
                  f"SAH {r['sah_cost']:.1f}{ratio}; BVH4 collapse (host) {r['bvh4_time_s']:.2f} s"
                  + (f", (device) {r['bvh4_device_time_s']:.2f} s" if device4 else ""), flush=True)
            del bvh
