"""Loading a scene and building what the enabled passes need, with progress on stderr."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from viewer.accel.builders import build_scene_bvh, resolve_builder
from viewer.accel.bvh import BVH
from viewer.scene import Scene


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclass
class PreparedScene:
    scene: Scene  # triangles in BVH leaf order (triangle id = slot)
    bvh: BVH


class BuildWork:
    """Fraction of a level-by-level BVH build done, for a progress bar whose ETA holds.

    Each level costs about as much as the triangles still above the leaves, so the work is
    sum over levels of active triangles; the triangles placed in leaves (all the builder reports)
    only grow near the end. After level L (about 2^(L+1) nodes below it) the active triangles sit
    in nodes of about active / 2^(L+1) each, and need about log2(that / 3) + 1 more levels
    (leaves hold 2..4 triangles)."""

    def __init__(self, n: int):
        self.n, self.level, self.done, self.active = max(int(n), 1), 0, 0.0, max(int(n), 1)

    def level_done(self, placed: int) -> float:
        self.done += self.active
        self.level += 1
        self.active = max(self.n - int(placed), 0)
        per_node = self.active / 2.0 ** min(self.level, 60)
        remaining = self.active * (np.log2(max(per_node / 3.0, 1.0)) + 1.0) if self.active else 0.0
        return min(self.done / (self.done + remaining), 1.0)


def recording_cameras(rec) -> list:
    """The cameras default lights are chosen for along a recording: every PATH_CAMERA_STEP-th
    frame and the last one (its keyframes alone can skip what the path turns towards)."""
    from viewer.default_lights import PATH_CAMERA_STEP

    count = rec.frame_count()
    frames = sorted(set(range(0, count, PATH_CAMERA_STEP)) | {count - 1})
    return [rec.camera_for_frame(n) for n in frames]


def prepare_scene_for_recording(rec, scene_size: int | None = None, seed: int | None = None,
                                mirror_patterns: list[str] | None = None, quiet: bool = False) -> PreparedScene:
    """The recording's scene, with default lights chosen for the recording's cameras."""
    from viewer.recording import resolve_scene_spec

    rs = resolve_scene_spec(rec)
    return prepare_scene(rs.spec, scene_size=scene_size if scene_size is not None else rs.size,
                         seed=rs.seed if rs.seed is not None else (seed if seed is not None else 1),
                         mirror_patterns=mirror_patterns, quiet=quiet, light_cameras=recording_cameras(rec))


def prepare_scene(spec: str | None, scene_size: int | None = None, seed: int = 1,
                  mirror_patterns: list[str] | None = None, quiet: bool = False,
                  bvh_builder: str | None = None, light_cameras: list | None = None) -> PreparedScene:
    """`light_cameras`: default lights (scenes without their own) light what these cameras see
    (a recording's path); None: what the default camera sees."""
    from viewer.scene_io import load_scene

    scene = load_scene(spec, scene_size=scene_size, seed=seed, mirror_patterns=mirror_patterns,
                       progress=not quiet)
    builder = resolve_builder(bvh_builder, scene.triangle_count)
    bar = tqdm(total=100, desc="BVH build", unit="%", bar_format="{l_bar}{bar}| [{elapsed}<{remaining}]",
               disable=quiet or scene.triangle_count < 200_000 or builder != "sah", file=sys.stderr, leave=False)
    work = BuildWork(scene.triangle_count)

    def progress(placed: int, total: int) -> None:
        bar.update(round(100 * work.level_done(placed)) - bar.n)

    bvh = build_scene_bvh(scene.triangles, builder, progress=progress)
    bar.close()
    st = bvh.stats
    if not quiet:
        log(f"scene {scene.name}: {scene.triangle_count:,} triangles, {len(scene.materials)} materials, "
            f"{len(scene.point_lights)} point / {len(scene.rect_lights)} area lights")
        log(f"BVH ({builder}): {st.nodes:,} nodes, depth {st.depth}, SAH cost {st.sah_cost:.1f}, "
            f"built in {st.build_time_s:.2f} s ({scene.triangle_count / max(st.build_time_s, 1e-9) / 1e6:.2f} Mtri/s), "
            f"{st.memory_bytes / 2**20:.1f} MiB of node + triangle buffers")
    ordered = scene.reordered(bvh.tri_order)
    if ordered.auto_lights:
        from viewer.default_lights import apply

        placed = apply(ordered, bvh, light_cameras)
        if placed is not None and not quiet:
            if light_cameras:
                log(f"default lights: {len(ordered.point_lights)} placed for {len(light_cameras)} cameras "
                    "along the recording")
            else:
                pos = ", ".join(f"{v:.3g}" for v in placed.position)
                log(f"default light at ({pos}): lights {100 * placed.lit:.0f}% of the surfaces the camera sees")
    return PreparedScene(ordered, bvh)
