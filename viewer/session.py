"""Loading a scene and building what the enabled passes need, with progress on stderr."""

from __future__ import annotations

import sys
from dataclasses import dataclass

from tqdm import tqdm

from viewer.accel.bvh import BVH, build_bvh
from viewer.scene import Scene


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclass
class PreparedScene:
    scene: Scene  # triangles in BVH leaf order (triangle id = slot)
    bvh: BVH


def prepare_scene(spec: str | None, scene_size: int | None = None, seed: int = 1,
                  mirror_patterns: list[str] | None = None, quiet: bool = False) -> PreparedScene:
    from viewer.scene_io import load_scene

    scene = load_scene(spec, scene_size=scene_size, seed=seed, mirror_patterns=mirror_patterns,
                       progress=not quiet)
    bar = tqdm(total=scene.triangle_count, desc="BVH build", unit="tri", unit_scale=True,
               disable=quiet or scene.triangle_count < 200_000, file=sys.stderr, leave=False)

    def progress(done: int, total: int) -> None:
        bar.update(done - bar.n)

    bvh = build_bvh(scene.triangles, progress=progress)
    bar.close()
    st = bvh.stats
    if not quiet:
        log(f"scene {scene.name}: {scene.triangle_count:,} triangles, {len(scene.materials)} materials, "
            f"{len(scene.point_lights)} point / {len(scene.rect_lights)} area lights")
        log(f"BVH: {st.nodes:,} nodes, depth {st.depth}, SAH cost {st.sah_cost:.1f}, "
            f"built in {st.build_time_s:.2f} s ({scene.triangle_count / max(st.build_time_s, 1e-9) / 1e6:.2f} Mtri/s), "
            f"{st.memory_bytes / 2**20:.1f} MiB of node + triangle buffers")
    return PreparedScene(scene.reordered(bvh.tri_order), bvh)
