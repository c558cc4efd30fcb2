"""CHC+RT fronts that live on the device: a steady pass plans, draws and refines without the host.

After a front's first (synchronous) pass has built its pair hierarchy on the host
(chcrt_front.PairFront), `attach` uploads it once; from then on every pass of that front is a fixed
chain of compute dispatches and indirect draws, whatever the tiles, pairs and subtrees:

  plan    chc_front_clear.comp    zero the tiles' plans and the pass's count slots
          chc_front_count.comp    per leaf pair: the finest tiles it covers count it
          chc_front_plan.comp     per tile: LCA fallback (heavy), item ranges, visible records,
                                  cull ranges, indirect draw / dispatch arguments (one work group)
          chc_front_scatter.comp  per leaf pair: listed on every tile it covers that is not heavy
          chc_front_items.comp    per listed pair (indirect): its item, in pair order within its tile
  (chcrt_pass_device.py draws: the visible records, the tiles' ray bounds, the cull, the survivors)
  pass    chc_front_passend.comp  the pass's ray and query counts into the frame's statistics
  refine  chc_front_refine.comp   the counts applied (visible / invisible / split), as ChcrtPass._refine
                                  (chcrt_pass_gpu.py)
          chc_front_merge.comp    invisibility pulled up one level, as PairFront.pull_up(1)
          chc_front_scan.comp     the next front's numbering (one work group)
          chc_front_write.comp    the next front written to the other buffer (ping-pong)

Nothing is read back within a frame. The frame's statistics (slot 0 of the META buffer) and each
front's size and overflow flags are read once, after the frame's own finish (`end_frame`), so they
cost no wait; the host sizes the buffers from them for the next frame (a front's leaf copies at
most double per pass, so twice the last copies always fit; its pairs at most quintuple). A pass
that would still overflow stays exact: items over capacity make every tile traverse its lowest
common ancestor, pairs over capacity are not split (their subtree is intersected whole).

Layouts (std430, little-endian, documented in chc_front.glsl): NODE_DTYPE per canonical BVH node,
PAIR_DTYPE per pair, TILE_BYTES per finest tile, META_INTS per meta slot.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.chcrt.chcrt_front import DEAD, INVISIBLE, VISIBLE, NodeTables, PairFront
from viewer.gl import io as glio
from viewer.gl.programs import compute_shader

HERE = Path(__file__).resolve().parent

# the device fronts' SSBO binding points (part of chcrt_layout.py's BINDINGS table, checked there)
FRONT_SSBO = {"BIND_FR_NODES": 20, "BIND_FR_PAIRS": 21, "BIND_FR_PAIRS_OUT": 22, "BIND_FR_TILES": 23,
              "BIND_FR_COUNTS": 24, "BIND_FR_FLAGS": 25, "BIND_FR_META": 26, "BIND_FR_TMP": 27,
              "BIND_FR_VIS_ITEMS": 28, "BIND_FR_INV_ITEMS": 29, "BIND_FR_RECORDS": 30, "BIND_FR_CULL": 31,
              "BIND_FR_ARGS": 32, "BIND_FR_SURVIVOR_CMD": 33}
B = FRONT_SSBO

NODE_DTYPE = np.dtype([("bmin", "<f4", 3), ("ref", "<i4"), ("bmax", "<f4", 3), ("gcount", "<i4"),
                       ("left", "<i4"), ("right", "<i4"), ("first", "<i4"), ("count", "<i4"),
                       ("height", "<i4"), ("area", "<f4"), ("pad", "<i4", 2)])
PAIR_DTYPE = np.dtype([("node", "<i4"), ("tile", "<i4"), ("parent", "<i4"), ("child", "<i4"),
                       ("kids", "<i4"), ("offset", "<i4"), ("pixels", "<i4"), ("age", "<i4")])
assert NODE_DTYPE.itemsize == 64 and PAIR_DTYPE.itemsize == 32
# per finest tile, one pass's plan (chc_front.glsl ChcTilePlan; read back by tests only)
TILE_PLAN_DTYPE = np.dtype([(name, "<i4") for name in (
    "cv", "ci", "lo", "hi", "heavy", "lca", "visBase", "visCount", "invBase", "invCount", "visFill", "invFill",
    "recBase", "nrec", "keptBase", "keptCount")])
TILE_BYTES = 64
assert TILE_PLAN_DTYPE.itemsize == TILE_BYTES
META_INTS = 16
META_N, META_OVERFLOW, META_HEAVY, META_COPIES, META_WANTED, META_TILES = range(6)
META_PROBE_FRONT, META_PROBE_FULL, META_PROBE_RAYS = 7, 8, 9  # the last pass's work probe (chc_front.glsl)
META_SPLITS = 10  # pairs the frame's refinement of the front split (a settling front: ChcrtParams.settle_splits)
DISCARD_SLOT = 1  # the statistics of a pass nobody reports (PassInfo.report) go here; fronts from slot 2
# slot 0 of META, summed over the frame's device passes (chc_front.glsl STAT_*)
STAT_NAMES = ("rays", "query_pixels", "query_records_drawn", "visible_pairs", "invisible_pairs", "inner_pairs",
              "lca_tiles", "requeries", "newly_visible_queries", "pull_ups", "subtrees_scheduled", "queries",
              "batches", "phase1_subtrees", "front_splits", "front_overflows")
# chc_front_plan.comp's arguments: the visible records' draw command at byte 0 (moderngl's
# render_indirect counts `first` in 20-byte steps whatever the command, so only 0 is used), the
# dispatches of chc_visorder.comp at 512 and chc_front_items.comp at 768, the item totals at 1024
ARGS_BYTES = 4 * 264
ARGS_VISORDER, ARGS_ITEMS = 512, 768
ARGS_PAIRS = 704  # the per-pair steps' dispatch, written by chc_front_clear.comp (chc_front.glsl ARG_PAIRS)
MIN_CAPACITY = 4096
# a refinement can make a front up to 5x larger (each ray-space split adds four children): a front's
# capacity is kept at 8x what it holds or wanted, and grows when 5x no longer fits
PAIR_GROWTH, PAIR_HEADROOM = 8, 5


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 1).bit_length()


def node_table(nt: NodeTables) -> np.ndarray:
    """NODE_DTYPE records of every canonical node (what the device front's shaders read)."""
    out = np.zeros(len(nt.left), NODE_DTYPE)
    out["bmin"] = nt.box_min
    out["bmax"] = nt.box_max
    out["ref"] = nt.gpu_ref
    out["gcount"] = nt.gpu_count
    out["left"] = nt.left
    out["right"] = nt.right
    out["first"] = nt.first
    out["count"] = nt.count
    out["height"] = nt.height
    out["area"] = nt.area32
    return out


def pack_front(f: PairFront) -> np.ndarray:
    """The live pairs of a host front as PAIR_DTYPE records, renumbered densely (links remapped)."""
    n = f.n
    alive = f.state[:n] != DEAD
    idx = np.flatnonzero(alive)
    new = np.full(n, -1, np.int64)
    new[idx] = np.arange(len(idx))
    out = np.zeros(len(idx), PAIR_DTYPE)
    out["node"] = f.node[idx]
    out["tile"] = (f.level[idx].astype(np.int32) << 24) | (f.ty[idx] << 12) | f.tx[idx]
    par, ch = f.parent[idx], f.child[idx]
    out["parent"] = np.where(par >= 0, new[np.maximum(par, 0)], -1)
    out["child"] = np.where(ch >= 0, new[np.maximum(ch, 0)], -1)
    out["kids"] = f.state[idx].astype(np.int32) | (f.nchild[idx].astype(np.int32) << 8)
    out["offset"] = f.offset[idx]
    out["pixels"] = f.pixels[idx]
    out["age"] = f.age[idx]
    return out


def leaf_copies(f: PairFront) -> int:
    """Leaf pairs copied onto finest tiles (a pair of level L covers 4^(max_level - L) of them)."""
    st = f.state[: f.n]
    leaf = (st == INVISIBLE) | (st == VISIBLE)
    return int((1 << (2 * (f.max_level - f.level[: f.n][leaf].astype(np.int64)))).sum())


@dataclass
class FrontMeta:
    """What the device reported of one front after a frame (META slot)."""

    n: int
    overflow: int
    heavy_tiles: int
    copies: int
    wanted: int
    tiles: int
    probe_front: int = 0  # work probe of the front's last pass, if it ran one (probe_rays > 0): box +
    probe_full: int = 0  # triangle tests of the sampled rays through the front and through the whole BVH
    probe_rays: int = 0
    splits: int = 0  # pairs the front's refinement split in the frame (its first pass's, shared fronts)


class DeviceFront:
    """One front's pairs on the device: two PAIR_DTYPE buffers (the current one and the next), its
    capacity in pairs and its META slot."""

    def __init__(self, ctx: moderngl.Context, slot: int, capacity: int, records: np.ndarray, settled: bool = True):
        self.slot = slot
        self.capacity = capacity
        # a front that started on the device (ChcrtParams.cold_start) is settling until a pass splits at most
        # settle_splits of its pairs (chcrt.py end_frame); one refined by the synchronous passes has settled
        self.settled = settled
        # its last plan sent full_bvh_fraction of the tiles to their ancestor: the passes trace the whole
        # BVH and only plan (chcrt.py sets it after each frame from META_HEAVY / META_TILES)
        self.full = False
        # work_probe: device passes so far (chcrt_pass_device.py), and whether the last measurement found
        # that the front saves too little work (set by chcrt.py end_frame: its passes then trace the whole
        # BVH between measurements)
        self.passes = 0
        self.wasteful = False
        self.work_ratio_full = 1.0  # the limit of its rays' type (ChcrtParams.work_ratio_full(_any))
        self.measured = False  # a pass measured since the last end_frame (its META row has the probe)
        # share_sample_fronts (chcrt_pass_device.py): the frame whose first pass of this front made the work probe's
        # decision, and whether that pass traced the whole BVH (the frame's later sample passes follow it)
        self.decided_frame = -1
        self.decided_wasted = False
        # a later sample pass of a frame shared this front (ChcrtParams.settle_probe: a settling front is
        # measured every frame only where later passes can follow the measurement)
        self.shared = False
        self.bufs = [ctx.buffer(reserve=capacity * PAIR_DTYPE.itemsize) for _ in range(2)]
        self.cur = 0
        if len(records):
            self.bufs[0].write(records.tobytes())
            iostats.to_device(records.nbytes)

    @property
    def current(self) -> moderngl.Buffer:
        return self.bufs[self.cur]

    def grow(self, ctx: moderngl.Context, capacity: int) -> None:
        """Room for `capacity` pairs, the current pairs copied on the device."""
        bufs = [ctx.buffer(reserve=capacity * PAIR_DTYPE.itemsize) for _ in range(2)]
        glio.host_barrier(ctx)  # the shaders' writes, before the copy reads them
        ctx.copy_buffer(bufs[0], self.current, size=self.capacity * PAIR_DTYPE.itemsize)
        for b in self.bufs:
            b.release()
        self.bufs, self.cur, self.capacity = bufs, 0, capacity

    def release(self) -> None:
        for b in self.bufs:
            b.release()
        self.bufs = []


class DeviceFronts:
    """The device fronts of one chcrt backend: the shared node table, scratch buffers and META
    buffer, and the dispatches of a pass (see the module docstring)."""

    def __init__(self, ctx: moderngl.Context, nt: NodeTables, bindings: dict[str, int]):
        """`bindings`: the backend's binding table (chcrt_layout.BINDINGS, FRONT_SSBO included)."""
        self.ctx = ctx
        defines = dict(bindings)
        names = ("clear", "count", "plan", "scatter", "items", "passend", "refine", "merge", "scan", "write")
        self.prog = {k: compute_shader(ctx, f"chc_front_{k}.comp", defines, (HERE,)) for k in names}
        self.nodes: moderngl.Buffer | None = None
        self.set_nodes(nt)
        self.meta_slots = 64
        self.meta = ctx.buffer(reserve=self.meta_slots * META_INTS * 4)
        self.meta_zero = ctx.buffer(bytes(META_INTS * 4))
        ctx.copy_buffer(self.meta, self.meta_zero)  # the frame's statistics start at zero
        self.free_slots = list(range(self.meta_slots - 1, DISCARD_SLOT, -1))
        self.fronts: dict[int, DeviceFront] = {}  # by META slot
        self.args = ctx.buffer(reserve=ARGS_BYTES)
        self.tiles_cap = self.vis_cap = self.inv_cap = self.rec_cap = self.flags_cap = self.cull_cap = 0
        self.tiles = self.vis_items = self.inv_items = self.tmp = self.records = self.flags = self.cull = None
        self.passes = 0  # device passes since the last end_frame
        # what the plan in the buffers (tile plans, items, records, arguments) was made for: (front
        # slot, frame, ray-batch size, tile level, cull sublevels), set by chcrt_pass_device.py after a plan that
        # is not `full`; any other plan resets it (share_sample_fronts)
        self.last_plan: tuple | None = None
        # what the cull's outputs in the buffers (survivors' records and command, kept items and ranges,
        # the pass's ray counts and three count slots) were made for, by the rays' reach alone, for
        # later samples with the same origins (chcrt_pass_device.py); every chcrt pass takes it and
        # resets it first, and only a pass that leaves those outputs as they are sets it again
        self.cull_key: tuple | None = None
        # the same for the ray counts in the counts buffer's ray slots (a later sample whose rays share
        # their origins and activity traces the whole BVH: it keeps them instead of counting again)
        self.rays_key: tuple | None = None
        self.ensure(tiles=64, pairs=MIN_CAPACITY, cull_tiles=64)  # every binding exists from the start

    def prewarm(self, zero: moderngl.Buffer) -> None:
        """Dispatch every program once with no work (`zero`: an indirect dispatch of 0 groups): a
        driver that compiles a compute shader's machine code at its first dispatch (llvmpipe) does
        so now, not in the first pass that plans on the device."""
        for prog in self.prog.values():
            prog.run_indirect(zero)
        iostats.gl_draw(len(self.prog))

    # -- buffers ----------------------------------------------------------------------------------
    def set_nodes(self, nt: NodeTables) -> None:
        """(Re)upload the node table: on creation and when the scene's boxes moved (a refit)."""
        table = node_table(nt)
        if self.nodes is not None:
            self.nodes.release()
        self.nodes = self.ctx.buffer(table.tobytes())
        iostats.to_device(table.nbytes)

    def ensure(self, tiles: int = 0, copies: int = 0, pairs: int = 0, cull_tiles: int = 0) -> None:
        """Scratch for `tiles` finest tiles, `copies` leaf copies per pass (twice that: a front's copies
        at most double per pass), fronts of `pairs` capacity and `cull_tiles` cull tiles."""
        items = _pow2(2 * copies + tiles + 1024)
        if tiles > self.tiles_cap:
            self.tiles_cap = _pow2(tiles)
            self._replace("tiles", self.tiles_cap * TILE_BYTES)
        if items > min(self.vis_cap, self.inv_cap):
            self.vis_cap = self.inv_cap = max(items, self.vis_cap)
            self.rec_cap = self.vis_cap + self.tiles_cap
            # visible items, then (merge_kept) the cull's kept invisible items at kept_offset
            self._replace("vis_items", (self.vis_cap + self.inv_cap) * 64)
            self._replace("inv_items", self.inv_cap * 64)
            self._replace("tmp", (self.vis_cap + self.inv_cap) * 8)
            self._replace("records", self.rec_cap * 32)
        if pairs > self.flags_cap:
            self.flags_cap = _pow2(pairs)
            self._replace("flags", self.flags_cap * 16)
        if cull_tiles > self.cull_cap:
            self.cull_cap = _pow2(cull_tiles)
            self._replace("cull", self.cull_cap * 32)

    @property
    def kept_offset(self) -> int:
        """Where, in vis_items, the cull writes the kept invisible items of a merging pass (merge_kept):
        the visible records and the merged kept pairs are read from one buffer."""
        return self.vis_cap

    def _replace(self, name: str, nbytes: int) -> None:
        old = getattr(self, name)
        if old is not None:
            old.release()
        setattr(self, name, self.ctx.buffer(reserve=max(nbytes, 16)))

    # -- fronts -------------------------------------------------------------------------------------
    def attach(self, f: PairFront, tiles: int, settled: bool = True) -> DeviceFront:
        """Upload host front `f` into a new device front, once its synchronous refinement is done, or
        as it starts, (screen, root), where the device refines it from the first pass (`settled`
        False: ChcrtParams.cold_start); one upload, once."""
        if not self.free_slots:
            self._grow_meta()
        slot = self.free_slots.pop()
        rec = pack_front(f)
        dev = DeviceFront(self.ctx, slot, _pow2(max(MIN_CAPACITY, PAIR_GROWTH * len(rec))), rec, settled)
        row = np.zeros(META_INTS, np.int32)
        row[META_N] = len(rec)
        # (after the shaders' writes to META: other fronts' passes of this frame, before a device cold start)
        glio.host_barrier(self.ctx)
        self.meta.write(row.tobytes(), offset=slot * META_INTS * 4)
        iostats.to_device(row.nbytes)
        self.ensure(tiles=tiles, copies=leaf_copies(f), pairs=dev.capacity)
        self.fronts[slot] = dev
        return dev

    def detach(self, dev: DeviceFront) -> None:
        self.fronts.pop(dev.slot, None)
        self.free_slots.append(dev.slot)
        dev.release()

    def _grow_meta(self) -> None:
        n = 2 * self.meta_slots
        meta = self.ctx.buffer(reserve=n * META_INTS * 4)
        glio.host_barrier(self.ctx)
        self.ctx.copy_buffer(meta, self.meta)
        self.meta.release()
        self.meta = meta
        self.free_slots += list(range(n - 1, self.meta_slots - 1, -1))
        self.meta_slots = n

    # -- one pass -----------------------------------------------------------------------------------
    def _program(self, name: str, uniforms: dict[str, object]) -> moderngl.ComputeShader:
        """Program `name` with the uniforms it declares set (the others are ignored)."""
        prog = self.prog[name]
        for k, v in uniforms.items():
            if prog.get(k, None) is not None:
                prog[k] = v
        return prog

    def _run(self, name: str, groups: int, **uniforms: object) -> None:
        self._program(name, uniforms).run(max(int(groups), 1))
        self._barrier()

    def _run_indirect(self, name: str, offset: int, **uniforms: object) -> None:
        self._program(name, uniforms).run_indirect(self.args, offset)
        self._barrier()

    def _barrier(self) -> None:
        # (the fragment shaders read the items through a buffer texture: texel fetches see storage
        # writes only after a barrier that names them; GL 4.5 glMemoryBarrier)
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
                                | moderngl.TEXTURE_FETCH_BARRIER_BIT)
        iostats.gl_draw()

    def _bind(self, dev: DeviceFront, counts: moderngl.Buffer) -> None:
        for name, buf in (("BIND_FR_NODES", self.nodes), ("BIND_FR_PAIRS", dev.current),
                          ("BIND_FR_PAIRS_OUT", dev.bufs[1 - dev.cur]), ("BIND_FR_TILES", self.tiles),
                          ("BIND_FR_COUNTS", counts), ("BIND_FR_FLAGS", self.flags), ("BIND_FR_META", self.meta),
                          ("BIND_FR_TMP", self.tmp), ("BIND_FR_VIS_ITEMS", self.vis_items),
                          ("BIND_FR_INV_ITEMS", self.inv_items), ("BIND_FR_RECORDS", self.records),
                          ("BIND_FR_CULL", self.cull), ("BIND_FR_ARGS", self.args)):
            buf.bind_to_storage_buffer(B[name])

    @staticmethod
    def stat_base(report: bool) -> int:
        """Where a pass's statistics go (the uniform statBase): the frame's, or the discarded slot."""
        return 0 if report else DISCARD_SLOT * META_INTS

    def clear(self, counts: moderngl.Buffer, survivor_cmd: moderngl.Buffer, *, ray_slots: int, capacity: int,
              slot: int = 0, n_tiles: int = 0, reset_meta: bool = True, keep_cull: bool = False,
              keep_rays: bool = False) -> None:
        """Zero the pass's count slots (`capacity` pair slots after `ray_slots` ray slots, then the
        pass's three), `n_tiles` tiles' plans, front `slot`'s overflow bits and work probe (0: no
        front; `reset_meta` False: kept, a shared front's later sample pass in the frame) and the
        survivors' draw command: the first dispatch of every device pass, also of a full-BVH one.
        `keep_cull`: the ray slots, the three and the command stay (a pass that takes the cull
        cull_key names); `keep_rays`: the ray slots stay (rays_key)."""
        counts.bind_to_storage_buffer(B["BIND_FR_COUNTS"])
        survivor_cmd.bind_to_storage_buffer(B["BIND_FR_SURVIVOR_CMD"])
        self.args.bind_to_storage_buffer(B["BIND_FR_ARGS"])
        self.tiles.bind_to_storage_buffer(B["BIND_FR_TILES"])
        self.meta.bind_to_storage_buffer(B["BIND_FR_META"])
        self.passes += 1
        self._run("clear", -(-max(n_tiles, ray_slots, 3) // 64), nTiles=n_tiles, capacity=capacity,
                  raySlots=ray_slots, frontSlot=slot, resetMeta=int(reset_meta), keepCull=int(keep_cull),
                  keepRays=int(keep_rays))

    def plan(self, dev: DeviceFront, counts: moderngl.Buffer, survivor_cmd: moderngl.Buffer, *, ray_slots: int,
             frame: int, max_level: int, size: tuple[int, int], threshold: int, requery_interval: int,
             max_batch: int, lca_pairs: int, lca_subtrees: int, heavy_allowed: bool, cull_sub: int,
             count_due_only: bool, seed: int, report: bool = True, full: bool = False,
             reset_meta: bool = True) -> None:
        """Plan: the pass's visible items and records, invisible items and cull ranges, and the
        indirect arguments (ARGS_*), from the front as it stands. Five dispatches. `full`: a pass that
        traces the whole BVH only refreshes the front's META (three dispatches, no statistics), so
        the host can decide again after the frame (the front does not change on such passes, but
        the aggressive mode's choice of pairs to test does). `reset_meta`: as clear's."""
        self.last_plan = None  # (set again by the caller for this plan)
        n_tiles = 1 << (2 * max_level)
        n_cull = 1 << (2 * (max_level + cull_sub))
        self.ensure(tiles=n_tiles, pairs=dev.capacity, cull_tiles=n_cull)
        common = dict(capacity=dev.capacity, raySlots=ray_slots, frontSlot=dev.slot, maxLevel=max_level,
                      threshold=int(threshold), frame=int(frame), requeryInterval=int(requery_interval),
                      visCap=self.vis_cap, seed=int(seed), statBase=self.stat_base(report and not full))
        self._bind(dev, counts)
        self.clear(counts, survivor_cmd, ray_slots=ray_slots, capacity=dev.capacity, slot=dev.slot, n_tiles=n_tiles,
                   reset_meta=reset_meta)
        self._run_indirect("count", ARGS_PAIRS, **common)  # (sized by the clear for the front's pairs)
        self._run("plan", 1, nTiles=n_tiles, raySize=tuple(size), maxBatch=int(max_batch), lcaPairs=int(lca_pairs),
                  lcaSubtrees=int(lca_subtrees), heavyAllowed=int(heavy_allowed), invCap=self.inv_cap,
                  recCap=self.rec_cap, cullSub=int(cull_sub), **common)
        if full:
            return
        self._run_indirect("scatter", ARGS_PAIRS, **common)
        self._run_indirect("items", ARGS_ITEMS, countDueOnly=int(count_due_only), **common)

    def pass_end(self, counts: moderngl.Buffer, *, ray_slots: int, capacity: int, report: bool = True) -> None:
        """The pass's active rays, query pixels and records drawn into the frame's statistics (after
        the pass's draws: their atomic counts made visible to it and to the refinement)."""
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        counts.bind_to_storage_buffer(B["BIND_FR_COUNTS"])
        self.meta.bind_to_storage_buffer(B["BIND_FR_META"])
        self._run("passend", 1, raySlots=ray_slots, capacity=capacity, statBase=self.stat_base(report))

    def refine(self, dev: DeviceFront, counts: moderngl.Buffer, *, ray_slots: int, frame: int, max_level: int,
               threshold: int, requery_interval: int, t_q: float, max_height: int, max_tris: int, seed: int,
               report: bool = True) -> None:
        """Refinement: the pass's counts applied, invisibility pulled up, the next front written to
        the other buffer, which becomes current. Four dispatches."""
        self._bind(dev, counts)
        common = dict(capacity=dev.capacity, raySlots=ray_slots, frontSlot=dev.slot, maxLevel=max_level,
                      threshold=int(threshold), frame=int(frame), requeryInterval=int(requery_interval),
                      seed=int(seed), statBase=self.stat_base(report))
        # (a work group per 64 pairs of the front as its pass's plan found it: ARGS_PAIRS)
        self._run_indirect("refine", ARGS_PAIRS, tQ=float(t_q), maxHeight=int(max_height), maxTris=int(max_tris),
                           **common)
        self._run_indirect("merge", ARGS_PAIRS, **common)
        self._run("scan", 1, **common)
        self._run_indirect("write", ARGS_PAIRS, **common)
        dev.cur = 1 - dev.cur

    # -- frame --------------------------------------------------------------------------------------
    def end_frame(self) -> tuple[dict[str, float], dict[int, FrontMeta]]:
        """After the frame's finish: the statistics of the device passes since the last call and each
        front's META row, in one read that waits for nothing (counted as bytes to the host, not as a
        host sync; the statistics are then zeroed on the device); the scratch and the fronts'
        capacities are grown for what they reported."""
        if self.passes == 0:
            return {}, {}
        self.passes = 0
        glio.host_barrier(self.ctx)  # the shaders' writes, before the read (no wait: the frame is finished)
        raw = np.frombuffer(self.meta.read(), np.int32).reshape(self.meta_slots, META_INTS)
        iostats.to_host(raw.nbytes)
        totals = raw[0].view(np.uint32)  # the shaders' int adds wrap as uint32 adds would
        stats = {name: float(totals[i]) for i, name in enumerate(STAT_NAMES) if name}
        self.ctx.copy_buffer(self.meta, self.meta_zero, size=META_INTS * 4)  # the next frame's start at zero
        rows: dict[int, FrontMeta] = {}
        for slot, dev in self.fronts.items():
            r = raw[slot]
            rows[slot] = FrontMeta(int(r[META_N]), int(r[META_OVERFLOW]), int(r[META_HEAVY]), int(r[META_COPIES]),
                                   int(r[META_WANTED]), int(r[META_TILES]), int(r[META_PROBE_FRONT]),
                                   int(r[META_PROBE_FULL]), int(r[META_PROBE_RAYS]), int(r[META_SPLITS]))
            m = rows[slot]
            if m.overflow & 1 or PAIR_HEADROOM * max(m.wanted, m.n) > dev.capacity:
                dev.grow(self.ctx, _pow2(PAIR_GROWTH * max(m.wanted, m.n)))
            self.ensure(copies=m.copies * (2 if m.overflow & 2 else 1), pairs=dev.capacity)
        return stats, rows

    def release(self) -> None:
        for dev in self.fronts.values():
            dev.release()
        self.fronts.clear()
        for obj in (self.nodes, self.meta, self.meta_zero, self.args, self.tiles, self.vis_items, self.inv_items,
                    self.tmp, self.records, self.flags, self.cull, *self.prog.values()):
            if obj is not None:
                obj.release()
