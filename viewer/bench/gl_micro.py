"""Synthetic GL micro-benchmark (shaders/bench_micro.*): what one draw, one occlusion query, one glFinish or one small
readback costs on this GL implementation, on the same context the studies use.

CHC+RT trades ray/box tests for draws and queries; on a CPU rasterizer those fixed costs decide
whether that pays, so `rtwalk bench-chcrt --study overhead` reports them beside its real runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from viewer.gl.bindings import BIND_MICRO
from viewer.gl.programs import load_shader_source


@dataclass
class MicroResult:
    """One synthetic GL operation: wall time per op, best of the trials (other jobs on a shared
    machine only ever add time), with the glFinish at the end amortised."""

    name: str
    ops_per_trial: int
    trials: int
    us_per_op: float  # wall, best trial, including the final glFinish
    submit_us_per_op: float  # CPU time to issue (before the final glFinish), same trial
    median_us_per_op: float  # wall, median of the trials
    items_per_op: int = 1  # instances / queries per op
    us_per_item: float = float("nan")
    check: str = ""
    trial_us_per_op: list[float] = field(default_factory=list)


_MICRO_GRID = (32, 32)
_MICRO_QUAD_PX = 4


def micro_overheads(ctx, size: tuple[int, int], scale: float = 1.0, trials: int = 7) -> tuple[list[MicroResult], dict]:
    """Per-draw / per-query costs of this GL implementation, on a target of the run's size.

    Tiles are 1/16 of the target per side (the finest CHC+RT tiles at the default
    min_tile_fraction are about that), cycled over the target so every draw also changes the
    scissor box, as chcrt's draws do."""
    import moderngl

    w, h = size
    tw, th = max(w // 16, 1), max(h // 16, 1)
    tiles = [(x * tw, y * th, tw, th) for y in range(16) for x in range(16)]
    prog = ctx.program(vertex_shader=load_shader_source("bench_micro.vert"),
                       fragment_shader=load_shader_source("bench_micro.frag"))
    vao = ctx.vertex_array(prog, [])
    color = ctx.texture(size, 4)
    fbo = ctx.framebuffer(color_attachments=[color])
    counts = ctx.buffer(reserve=4 * 1024)
    zeros = bytes(4 * 1024)
    gx, gy = _MICRO_GRID
    prog["grid"].value = (gx, gy)
    q = _MICRO_QUAD_PX  # the grid spans the target, so no instance is clipped (each covers q*q pixels)
    prog["cell"].value = (2.0 * max(w - q, 0) / (w * (gx - 1)), 2.0 * max(h - q, 0) / (h * (gy - 1)))
    prog["quad"].value = (2.0 * _MICRO_QUAD_PX / w, 2.0 * _MICRO_QUAD_PX / h)
    prog["value"].value = (0.2, 0.4, 0.6, 1.0)
    prog["countAtomics"].value = 0
    prog["instanced"].value = 0
    ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
    fbo.use()
    n_q = max(int(400 * scale), 8)
    queries = [ctx.query(samples=True) for _ in range(n_q)]
    results: list[MicroResult] = []

    def n_of(base: int) -> int:
        return max(int(base * scale), 4)

    def measure(name: str, ops: int, body: Callable[[int], None], items: int = 1, check: str = "") -> MicroResult:
        body(min(ops, 8))  # warm up (first use allocates)
        ctx.finish()
        walls, submits = [], []
        for _ in range(trials):
            ctx.finish()
            t0 = time.perf_counter()
            body(ops)
            t1 = time.perf_counter()
            ctx.finish()
            t2 = time.perf_counter()
            walls.append((t2 - t0) / ops * 1e6)
            submits.append((t1 - t0) / ops * 1e6)
        best = int(np.argmin(walls))
        us = float(walls[best])
        r = MicroResult(name, ops, trials, us, float(submits[best]), float(np.median(walls)), items, us / items,
                        check, [float(v) for v in walls])
        results.append(r)
        return r

    def tiled_draws(n: int) -> None:
        prog["instanced"].value = 0
        for i in range(n):
            fbo.scissor = tiles[i % len(tiles)]
            vao.render(moderngl.TRIANGLES, vertices=3)

    def uniform_draws(n: int) -> None:
        prog["instanced"].value = 0
        u = prog["value"]
        for i in range(n):
            fbo.scissor = tiles[i % len(tiles)]
            u.value = ((i % 97) / 97.0, 0.4, 0.6, 1.0)
            vao.render(moderngl.TRIANGLES, vertices=3)

    def full_draws(n: int) -> None:
        prog["instanced"].value = 0
        fbo.scissor = None
        for _ in range(n):
            vao.render(moderngl.TRIANGLES, vertices=3)

    def query_sync(n: int) -> None:
        prog["instanced"].value = 0
        for i in range(n):
            fbo.scissor = tiles[i % len(tiles)]
            q = queries[i % n_q]
            with q:
                vao.render(moderngl.TRIANGLES, vertices=3)
            _ = q.samples

    def query_batch(n: int) -> None:
        prog["instanced"].value = 0
        for s in range(0, n, n_q):
            used = queries[: min(n_q, n - s)]
            for i, q in enumerate(used):
                fbo.scissor = tiles[(s + i) % len(tiles)]
                with q:
                    vao.render(moderngl.TRIANGLES, vertices=3)
            for q in used:
                _ = q.samples

    def instanced(k: int) -> Callable[[int], None]:
        def body(n: int) -> None:
            prog["instanced"].value = 1
            fbo.scissor = None
            for _ in range(n):
                vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=k)
        return body

    last_counts: dict[int, np.ndarray] = {}

    def atomic_queries(k: int) -> Callable[[int], None]:
        def body(n: int) -> None:
            prog["instanced"].value = 1
            prog["countAtomics"].value = 1
            fbo.scissor = None
            counts.bind_to_storage_buffer(BIND_MICRO)
            for _ in range(n):
                counts.write(zeros)
                vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=k)
                ctx.memory_barrier()
                last_counts[k] = np.frombuffer(counts.read(size=4 * k), np.uint32)
            prog["countAtomics"].value = 0
        return body

    def finishes(n: int) -> None:
        for _ in range(n):
            ctx.finish()

    def small_reads(n: int) -> None:
        prog["instanced"].value = 0
        for i in range(n):
            fbo.scissor = tiles[i % len(tiles)]
            vao.render(moderngl.TRIANGLES, vertices=3)
            counts.read(size=64)

    tile_txt = f"{tw}x{th} px tile"
    try:
        measure("glFinish, idle pipeline", n_of(400), finishes)
        measure(f"draw, {tile_txt} (scissor change + draw)", n_of(2000), tiled_draws)
        measure(f"draw + uniform change, {tile_txt}", n_of(2000), uniform_draws)
        measure(f"draw, whole {w}x{h} target", n_of(100), full_draws)
        measure(f"draw + 64-byte buffer read (one round trip), {tile_txt}", n_of(200), small_reads)
        measure(f"occlusion query one at a time (begin, draw {tile_txt}, end, read)", n_of(400), query_sync)
        measure(f"occlusion queries, {n_q} issued then all read, {tile_txt}", n_q, query_batch)
        for k in (1, 64, 1024):
            measure(f"instanced draw, {k} x {_MICRO_QUAD_PX}x{_MICRO_QUAD_PX} px instances",
                    n_of(200 if k < 1024 else 60), instanced(k), items=k)
        for k in (64, 1024):
            r = measure(f"{k} queries in one instanced draw, counted by SSBO atomics, + barrier + read",
                        n_of(100 if k < 1024 else 40), atomic_queries(k), items=k)
            got = last_counts.get(k)
            expect = _MICRO_QUAD_PX * _MICRO_QUAD_PX
            r.check = ("counts ok" if got is not None and np.all(got == expect)
                       else f"unexpected counts (want {expect} per instance)")
        q = queries[0]
        fbo.scissor = tiles[0]
        prog["instanced"].value = 0
        with q:
            vao.render(moderngl.TRIANGLES, vertices=3)
        for r in results:
            if "occlusion" in r.name:
                r.check = "samples ok" if q.samples == tw * th else f"samples {q.samples} != {tw * th}"
    finally:
        fbo.scissor = None
        prog["countAtomics"].value = 0
        for obj in (vao, fbo, color, counts, prog):
            obj.release()
    return results, {"target": list(size), "tile": [tw, th], "trials": trials, "queries_in_flight": n_q}

