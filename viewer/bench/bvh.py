"""`rtwalk bench-bvh`: BVH build throughput and quality on the procedural city."""

from __future__ import annotations

import argparse

from viewer.bench.common import add_count_option

HELP = "BVH build throughput on the city scene"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_count_option(p, "--triangles", "1000000,5000000",
                     "city triangle counts to build (each as --scene-size accepts)")
    p.add_argument("--seed", type=int, default=1, help="seed of the procedural city")
    p.add_argument("--out", default="out/bench", help="folder for bvh-build.json")


def run(args: argparse.Namespace) -> int:
    from viewer.accel.bvh import bench_build
    from viewer.bench.report import write_json
    from viewer.cli_args import check_output_dir, parse_sizes
    from viewer.procedural import make_city

    sizes = parse_sizes(args.triangles, flag="--triangles")
    out = check_output_dir(args.out, "--out")
    rows = []
    for n in sizes:
        scene = make_city(n, args.seed)
        r = bench_build(scene.triangles)
        r["target"] = n
        rows.append(r)
        print(f"city {scene.triangle_count:>10,} tris: build {r['build_time_s']:.2f} s "
              f"({r['throughput_mtris_per_s']:.2f} Mtri/s), {r['nodes']:,} nodes, depth {r['depth']}, "
              f"SAH {r['sah_cost']:.1f}", flush=True)
    write_json(out / "bvh-build.json", rows)
    print(f"report: {out / 'bvh-build.json'}")
    return 0
