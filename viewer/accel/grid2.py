"""Two-level grid (Kalojanov, Billeter & Slusallek 2011) for the teapot-in-a-stadium case.

A uniform grid (viewer.accel.grid, its layout untouched: pgrid and voxelwalk read the same top
cells) sized for the whole scene puts a small detailed object into one cell. Here every dense top
cell (at least `min_small` small triangles) also gets a sub-grid, built on the device from the
top-level pairs with a fixed number of launches (kernels: grid2_build.cl beside this file; layout
and nested walk: viewer/cl/kernels/grid2.cl):

  per top cell: classify its triangles, flag cells with enough small ones; scan -> sub-grid ids;
  per sub-grid: box = union of the small triangles' boxes (padded), ~`density` cells per small
  triangle shaped like that box; scan of the cell counts -> first sub-cell ids;
  per top pair: count the sub-cell pairs of a small triangle, flag a big one; two scans;
  (their totals come back with the top build's last wait, no wait of their own: they size the
  buffers and are checked against viewer.cl.limits)
  per top pair: write the sub pairs (global sub-cell id, triangle) and the big lists; radix sort,
  segments and cell ranges as in the top grid; SoA blocks of the sub-cells and of the big lists.

"Big" (box spanning >= `big_frac` top cells on some axis: the ground under the object) stays in a
short per-cell list tested once per visit, so it neither stretches the sub-grid's box to the whole
cell nor is listed in every sub-cell. Why a sub-grid sized only by count over the whole top cell
fails on this scene: docs/results/grids-far-and-mixed.md.

Memory: the sub-level's buffers are estimated from the device totals before allocation and must
fit the per-buffer limit and what the top level left of the budget; over it the sub density is
lowered (a few rounds, each one more wait), and at worst no sub-grids are made (the top grid alone,
as before; counter grid2_shrunk).

Extra layouts (device buffers; GRID_DTYPE header, cells, refs, blocks as in grid.py):
  sub_of  : int32 (ncells,): the top cell's sub-grid or -1
  subs    : SUBGRID_DTYPE (nsub,)
  scells  : uint32 (nsubcells, 2): first ref, count; scb: uint32 (nsubcells,) first block;
  sblocks : GRID_BLOCK_DTYPE: the sub-cells' triangles four at a time
  bblocks : GRID_BLOCK_DTYPE: the big lists' triangles four at a time (subs[s].big = first block, count)
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from viewer.accel.grid import GRID_BLOCK_DTYPE, PAIR_BYTES, WG, GridSpec, GridStats, UniformGrid
from viewer.cl import io as clio
from viewer.cl.limits import DeviceLimits, device_limits
from viewer.cl.primitives import Chunks

KERNEL = Path(__file__).resolve().parent / "grid2_build.cl"

SUBGRID_DTYPE = np.dtype([("lo", "<f4", 4), ("cell", "<f4", 4), ("res", "<i4", 4), ("big", "<u4", 4)])
assert SUBGRID_DTYPE.itemsize == 64


# Top cells per triangle of a two-level grid (Kalojanov, Billeter & Slusallek 2011: a coarse top
# level, fine sub-grids where the triangles are): with the one-level density (2) a 1e-3 object on a
# 2e4 ground left rays crossing ~100 empty top cells (docs/results/grids-far-and-mixed.md)
TOP_DENSITY = 0.25


@dataclass
class SubSpec:
    """Which top cells get a sub-grid and how fine it is."""

    min_small: int = 16  # small triangles a top cell needs for a sub-grid
    big_frac: float = 0.5  # a triangle spanning this many top cells on an axis is "big"
    density: float = 1.0  # sub-cells per small triangle (docs/results/grids-far-and-mixed.md: measured)
    max_axis: int = 256
    max_cells: int = 2**21  # per sub-grid


@dataclass
class Grid2Stats(GridStats):
    subgrids: int = 0
    subcells: int = 0
    subpairs: int = 0
    big: int = 0
    shrunk: int = 0  # sub density halvings taken to fit the memory budget

    def as_dict(self) -> dict[str, float]:
        d = super().as_dict()
        d.update({"grid2_subgrids": float(self.subgrids), "grid2_subcells": float(self.subcells),
                  "grid2_subpairs": float(self.subpairs), "grid2_big": float(self.big),
                  "grid2_shrunk": float(self.shrunk)})
        return d


def sub_bytes(top_pairs: int, ncells: int, nsub: int, subcells: int, subpairs: int, big: int) -> tuple[int, int]:
    """(total, largest buffer) bytes of the sub level (module docstring)."""
    sblocks = GRID_BLOCK_DTYPE.itemsize * (subpairs // 4 + min(subpairs, subcells) + 1)
    bblocks = GRID_BLOCK_DTYPE.itemsize * (big // 4 + nsub + 1)
    per_top = 8 * top_pairs + 12 * ncells  # counts, big flags; flags, ids, sub_of
    per_sub = (SUBGRID_DTYPE.itemsize + 16) * nsub
    total = per_top + per_sub + PAIR_BYTES * subpairs + 12 * min(subpairs, subcells) + 12 * subcells + sblocks \
        + bblocks + 4 * big
    return total, max(4 * subpairs, sblocks, bblocks, 8 * subcells, 4 * top_pairs, 4 * ncells)


class TwoLevelGrid(UniformGrid):
    """A UniformGrid (same top-level buffers) plus sub-grids for its dense cells."""

    def __init__(self, ctx: Any = None, prims: Any = None, sub: SubSpec | None = None):
        from viewer.cl import build

        super().__init__(ctx, prims)
        self.sub = sub or SubSpec()
        prog = build(KERNEL, {"WG": WG}, self.ctx)
        self._k2 = {name: clio.kernel(prog, name) for name in ("g2_flags", "g2_setup", "g2_pair_count",
                                                              "g2_pair_write", "g2_big_ranges", "g2_finish")}
        self._density = self.sub.density
        self._sub_got = np.zeros(4, np.uint32)  # the sub level's totals (_sub_read)
        self.stats: Grid2Stats | None = None

    def _run2(self, name: str, n: int, *args: Any) -> None:
        if n:
            self._k2[name](self.ctx.queue, (-(-n // WG) * WG,), (WG,), *args)

    @property
    def sub_of(self) -> Any:
        return self._bufs["sub_of"]

    @property
    def subs(self) -> Any:
        return self._bufs["subs"]

    @property
    def scells(self) -> Any:
        return self._bufs["scells"]

    @property
    def sblocks(self) -> Any:
        return self._bufs["sblocks"]

    @property
    def scb(self) -> Any:
        return self._bufs["scb"]

    @property
    def bblocks(self) -> Any:
        return self._bufs["bblocks"]

    def build(self, tris: Any, n: int, lo: np.ndarray, hi: np.ndarray, spec: GridSpec | None = None,
              limits: DeviceLimits | None = None) -> Grid2Stats:
        """The top grid (UniformGrid.build; the sub level's counting rides on its last wait), then
        the sub level's pairs, sort and blocks with no further wait."""
        t0 = time.perf_counter()
        lim = limits or device_limits(self.ctx)
        self._density = self.sub.density
        top = super().build(tris, n, lo, hi, spec, lim)
        got = tuple(int(x) for x in self._sub_got)
        density, shrunk = self.sub.density, 0
        while True:
            total, largest = sub_bytes(top.pairs, top.cells, *got)
            if (largest <= lim.max_alloc and total <= lim.budget - top.nbytes) or density == 0.0:
                break
            shrunk += 1
            density = density / 8 if shrunk < 4 else 0.0  # 0: no sub-grids (the top grid alone)
            self._sub_count(tris, self._bufs["count_pairs"], max(top.pairs, 1), top.cells, density)
            got = tuple(int(x) for x in self._sub_read(blocking=True))
        nsub, subcells, subpairs, big = got
        if nsub:
            self._sub_write(tris, top, nsub, subcells, subpairs, big)
        else:  # the walk's arguments exist (every sub_of is -1)
            for name in ("scells", "scb", "sblocks", "bblocks"):
                self._buf(name, 16)
        st = Grid2Stats(top.res, top.cells, top.pairs, top.nonempty, (time.perf_counter() - t0) * 1e3,
                        top.coarsened, top.nbytes + total, nsub, subcells, subpairs, big, shrunk)
        self.stats = st
        return st

    def _before_last_wait(self, tris: Any, n_pairs: Any, bound: int, ncells: int) -> None:
        """The sub level's counting, its totals read back with the top build's last wait."""
        if isinstance(n_pairs, int):  # the exact build knows its pairs on the host
            n_pairs = self._count_buf("pairs", n_pairs)
        self._sub_count(tris, n_pairs, bound, ncells, self._density)
        self._sub_read(blocking=False)

    def _sub_read(self, blocking: bool) -> np.ndarray:
        """Sub-grids, sub-cells, sub pairs, big pairs (device totals) into self._sub_got."""
        self._sub_got = got = np.zeros(4, np.uint32)
        q = self.ctx.queue
        for k, name in enumerate(("nsub", "subcells", "subpairs", "big")):
            clio.copy(q, got[k:k + 1], self._bufs[f"count_{name}"], is_blocking=blocking and k == 3)
        return got

    def _sub_count(self, tris: Any, n_pairs: Any, P: int, ncells: int, density: float) -> None:
        """Flags, sub-grid records and per-pair counts of the first *n_pairs (<= P) sorted top
        pairs, and their scans (no wait)."""
        u, f = np.uint32, np.float32
        sp = self.sub
        min_small = u(sp.min_small if density > 0 else 0xFFFFFFFF)
        flags = self._buf("g2_flags", 4 * ncells)
        self._run2("g2_flags", ncells, self.header, self.cells, self.refs, tris, u(ncells), min_small,
                   f(sp.big_frac), flags)
        subidx = self._buf("g2_subidx", 4 * ncells)
        self.prims.exclusive_scan_dev(flags, subidx, self._count_buf("ncells2", ncells), ncells,
                                      self._count_buf("nsub"))
        nsub_bound = max(1, min(ncells, P // max(sp.min_small, 1) + 1))
        sub_of = self._buf("sub_of", 4 * ncells)
        subs = self._buf("subs", SUBGRID_DTYPE.itemsize * nsub_bound)
        nsubc = self._buf("g2_nsubc", 4 * nsub_bound)
        self._run2("g2_setup", ncells, self.header, self.cells, self.refs, tris, u(ncells), min_small,
                   f(sp.big_frac), f(max(density, 1e-6)), np.int32(sp.max_axis), u(sp.max_cells), flags, subidx,
                   sub_of, subs, nsubc)
        sub_base = self._buf("g2_sub_base", 4 * nsub_bound)
        self.prims.exclusive_scan_dev(nsubc, sub_base, self._bufs["count_nsub"], nsub_bound,
                                      self._count_buf("subcells"))
        cnt = self._buf("g2_cnt", 4 * P)
        bigf = self._buf("g2_bigf", 4 * P)
        self._run2("g2_pair_count", P, self.header, self._buf("keys", 4 * P), self._buf("vals", 4 * P), tris,
                   n_pairs, sub_of, subs, f(sp.big_frac), cnt, bigf)
        self.prims.exclusive_scan_dev(cnt, cnt, n_pairs, P, self._count_buf("subpairs"))
        self.prims.exclusive_scan_dev(bigf, bigf, n_pairs, P, self._count_buf("big"))

    def _sub_write(self, tris: Any, top: GridStats, nsub: int, subcells: int, subpairs: int, big: int) -> None:
        """Pairs, sort, ranges and blocks of the sub level (no wait)."""
        cl, q, u, f = self.ctx.cl, self.ctx.queue, np.uint32, np.float32
        P, ncells = top.pairs, top.cells
        keys2 = self._buf("g2_keys", 4 * max(subpairs, 1))
        vals2 = self._buf("g2_vals", 4 * max(subpairs, 1))
        bigrefs = self._buf("g2_bigrefs", 4 * max(big, 1))
        n_pairs = self._bufs["count_pairs"]
        self._run2("g2_pair_write", P, self.header, self._bufs["keys"], self.refs, tris, n_pairs, self.sub_of,
                   self.subs, self._bufs["g2_sub_base"], f(self.sub.big_frac), self._bufs["g2_cnt"],
                   self._bufs["g2_bigf"], keys2, vals2, bigrefs)
        bigcells = self._buf("g2_bigcells", 8 * nsub)
        self._run2("g2_big_ranges", ncells, self.cells, self.sub_of, self._bufs["g2_bigf"], self._bufs["count_big"],
                   n_pairs, u(ncells), bigcells)
        scells = self._buf("scells", 8 * subcells)
        cl.enqueue_fill_buffer(q, scells, u(0), 0, 8 * subcells)
        if subpairs:
            self.prims.sort_pairs(keys2, vals2, subpairs, key_bits=max(1, (subcells - 1).bit_length()))
            m = min(subpairs, subcells)
            chunks = Chunks(0, self._buf("g2_seg_key", 4 * m), self._buf("g2_seg_start", 4 * m),
                            self._buf("g2_seg_len", 4 * m))
            seg = self.prims.segments_dev(keys2, self._count_buf("subpairs_n", subpairs), subpairs, None, chunks,
                                          self._count_buf("g2_nonempty"))
            self._run("grid_ranges", m, seg.key, seg.start, seg.length, self._bufs["count_g2_nonempty"], scells)
        scb = self._buf("scb", 4 * subcells)
        self._run("grid_block_counts", subcells, scells, u(subcells), scb)
        self.prims.exclusive_scan_dev(scb, scb, self._count_buf("subcells_n", subcells), subcells,
                                      self._count_buf("g2_nblocks"))
        sblocks = self._buf("sblocks", GRID_BLOCK_DTYPE.itemsize * (subpairs // 4 + min(subpairs, subcells) + 1))
        if subpairs:
            self._run("grid_blocks", subcells, scells, scb, vals2, tris, u(subcells), sblocks)
        bstart = self._buf("g2_bstart", 4 * nsub)
        self._run("grid_block_counts", nsub, bigcells, u(nsub), bstart)
        self.prims.exclusive_scan_dev(bstart, bstart, self._count_buf("nsub_n", nsub), nsub,
                                      self._count_buf("g2_nbblocks"))
        bblocks = self._buf("bblocks", GRID_BLOCK_DTYPE.itemsize * (big // 4 + nsub + 1))
        if big:
            self._run("grid_blocks", nsub, bigcells, bstart, bigrefs, tris, u(nsub), bblocks)
        self._run2("g2_finish", nsub, self.subs, self._bufs["g2_sub_base"], bstart, bigcells, u(nsub))

    def sub_to_numpy(self) -> dict[str, np.ndarray]:
        """The sub level copied from the device (tests, studies)."""
        st = self.stats
        assert st is not None, "build first"
        q = self.ctx.queue
        out = {"sub_of": np.empty(st.cells, np.int32), "subs": np.empty(st.subgrids, SUBGRID_DTYPE),
               "scells": np.empty((st.subcells, 2), np.uint32)}
        clio.copy(q, out["sub_of"], self.sub_of)
        if st.subgrids:
            clio.copy(q, out["subs"], self.subs)
            clio.copy(q, out["scells"], self.scells)
        return out
