"""chcrt, the GPU-driven pass on a host front (no device fronts: device_front=0, or a device that
cannot hold them): the host plans the records, the device culls and counts, the host reads the
counts once and refines the front. Mixed into ChcrtPass (chcrt_pass.py), whose state and shared
steps it uses."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.chcrt.chcrt_front import INVISIBLE, VISIBLE, to_finest_tiles
from viewer.backends.chcrt.chcrt_layout import (
    BIND_CHC_CANDIDATES,
    BIND_CHC_DRAWS,
    BIND_CHC_INDIRECT,
    BIND_CHC_QUERY_COUNTS,
    COUNT_BYTES,
    COUNT_SLOTS,
    DRAW_DTYPE,
    ITEM_DTYPE,
)
from viewer.gl import io as glio
from viewer.screen_tiles import tile_rects


class GpuDrivenSteps:
    """The GPU-driven pass with the front on the host."""

    def _run_gpu(self) -> None:
        """One pass in a fixed number of launches: the visible pairs (1 draw), the ray bounds of every
        finest tile (1 dispatch), the cull of the invisible pairs against them (1 dispatch) and the
        intersection of the survivors (1 indirect draw). The query is the intersection itself: a
        ray that enters a pair's box before its nearest hit so far counts into the pair's slot (the
        query's pass condition), so no separate query pass runs. One read of the counts at the end;
        the front is refined on the host for the next frame."""
        be, f = self.be, self.front
        prof = be.bc.profiler
        with prof.phase("chc:1-intersect-visible"):
            visible = f.leaves(VISIBLE)
            invisible = f.leaves(INVISIBLE)
            if self.threshold > 0 and len(invisible):
                # aggressive mode: a pair culled before (<= threshold rays entered) is not tested again
                # until its re-query is due
                invisible = invisible[(f.age[invisible] == 0) | f.requery_due(invisible, self.frame_number())]
            nslots = len(visible) + len(invisible)
            need = COUNT_BYTES + 4 * (nslots + 3)
            if be.gpu_counts.size < need:
                be.gpu_counts.release()
                be.gpu_counts = self.ctx.buffer(reserve=1 << (need - 1).bit_length())
            self._bind()
            self._init()
            be.gpu_counts.write(bytes(4 * (nslots + 3)), offset=COUNT_BYTES)
            iostats.to_device(4 * (nslots + 3))
            be.gpu_counts.bind_to_storage_buffer(BIND_CHC_QUERY_COUNTS, COUNT_BYTES, 4 * (nslots + 3))
            inv_copies = None
            full = f.full_bvh  # its synchronous refinement found the rays incoherent (cold_full_bvh)
            if full:
                pass
            elif self.p.lca_invisible and self.p.merge_tiles:
                vis_items, inv_copies = self._tile_plan(visible, invisible)
                n = 1 << f.max_level
                full = 0 < self.p.full_bvh_fraction <= self.stats["lca_tiles"] / (n * n)
                if not full:
                    nd, tile, sl = vis_items
                    self._draw_finest(nd, tile, self._due_slots(visible, sl))
            else:
                self._draw_subtrees(visible, self._due_slots(visible, np.arange(len(visible))))
            self.stats["phase1_subtrees"] = 0 if full else len(visible)
            self._sync()
        self._queries_and_traversal(full, lambda: self._cull_invisible(invisible, len(visible), nslots, inv_copies))
        with prof.phase("chc:4-final-intersect"):
            raw = np.frombuffer(glio.read(be.gpu_counts, size=COUNT_BYTES + 4 * (nslots + 3)),
                                np.uint32).astype(np.int64)
            self.stats["rays"] = int(raw[:COUNT_SLOTS].sum())
            cnt = raw[COUNT_SLOTS:]
            self.stats["query_pixels"] = int(cnt[nslots])
            self.stats["query_records_drawn"] = int(cnt[nslots + 1])
            self.rays_read = True
            if not full:  # a full-BVH pass counted nothing: the front stays as it is
                self._refine(visible, invisible, cnt[:nslots])

    def _due_slots(self, visible: np.ndarray, sl: np.ndarray) -> np.ndarray:
        """Count slots of visible-pair items (index into `visible`, -1 = not counted): with
        count_due_only, only pairs whose re-query is due this frame keep theirs (_refine reads no
        other visible pair's count), so the other items cost no atomic per entering ray."""
        if not self.p.count_due_only or len(visible) == 0:
            return sl
        due = self.front.requery_due(visible, self.frame_number())
        ok = sl >= 0
        ok[ok] = due[sl[ok]]
        return np.where(ok, sl, -1)

    def _cull_invisible(self, invisible: np.ndarray, slot0: int, nslots: int,
                        copies: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
        """Upload the invisible pairs copied onto the finest tiles they cover (intersection items
        with their count slots, sorted by tile), then on the GPU: per finest tile the rays' origin box
        and farthest reach (chc_tilebounds.comp), and per finest tile the pairs some ray may still
        enter (chc_querycull.comp), as records of the indirect intersection draw. `copies` (node,
        finest tile, slot): the copies left by _tile_plan (those of LCA tiles dropped). With
        cull_sublevels the bounds, the cull and the records are per sub-tile (each reads its finest
        tile's pairs): rays near a short hit no longer share a tile with far-reaching ones."""
        be, ctx, f = self.be, self.ctx, self.front
        level = f.max_level
        n = 1 << level
        ntiles = n * n
        if copies is None:
            nd, _, tx, ty, sl = to_finest_tiles(
                f.node[invisible].astype(np.int64), f.level[invisible].astype(np.int64),
                f.tx[invisible].astype(np.int64), f.ty[invisible].astype(np.int64),
                slot0 + np.arange(len(invisible), dtype=np.int64), level)
            tile = ty * n + tx
        else:
            nd, tile, sl = copies
        self.n_survivor_groups = len(nd)
        self.stats["queries"] += len(invisible)
        if not len(nd):
            return
        order = np.argsort(tile, kind="stable")
        be.items.upload(self._subtree_items(nd[order], sl[order]))
        be.bind_items(be.items.buf)
        counts = np.bincount(tile, minlength=ntiles)
        sub = int(self.p.cull_sublevels)
        while sub > 0 and min(self.size) >> (level + sub) < 4:
            sub -= 1
        cl = level + sub  # the cull's tile level
        m = 1 << cl
        nsub = m * m
        all_t = np.arange(nsub)
        sx, sy = all_t % m, all_t // m
        parent = (sy >> sub) * n + (sx >> sub)
        ranges = np.zeros(nsub, DRAW_DTYPE)
        ranges["rect"] = tile_rects(np.full(nsub, cl), sx, sy, self.size)
        ranges["info"][:, 0] = (np.cumsum(counts) - counts)[parent]
        ranges["info"][:, 1] = counts[parent]
        mb = self.p.max_batch
        need = max(int((-(-counts // mb)).sum()) << (2 * sub), 1) * DRAW_DTYPE.itemsize
        if be.survivors.size < need:
            be.survivors.release()
            be.survivors = ctx.buffer(reserve=1 << (need - 1).bit_length())
        need = max(len(nd) << (2 * sub), 1) * ITEM_DTYPE.itemsize
        if be.kept_boxes.size < need:
            be.kept_boxes.release()
            be.kept_boxes = ctx.buffer(reserve=1 << (need - 1).bit_length())
        be.all_queries.upload(ranges)
        be.query_indirect.write(np.array([6, 0, 0, 0], np.uint32).tobytes())
        iostats.to_device(16)
        be.kept_boxes.bind_to_storage_buffer(BIND_CHC_CANDIDATES)
        be.survivors.bind_to_storage_buffer(BIND_CHC_DRAWS)
        be.query_indirect.bind_to_storage_buffer(BIND_CHC_INDIRECT)
        self._tile_bounds(cl, nsub)  # after the visible pairs' bestBits
        be.querycull["nQueries"] = nsub
        be.querycull["maxItems"] = mb
        be.querycull["pixelSlot"] = nslots
        be.querycull["cull"] = int(self.p.coarse_cull)
        be.querycull["sortByGap"] = int(self.p.gap_order)
        be.querycull["coneCull"] = int(self.p.cone_cull)
        be.querycull.run(-(-nsub // 64))
        ctx.memory_barrier(moderngl.COMMAND_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT
                           | moderngl.TEXTURE_FETCH_BARRIER_BIT)
        self.stats["draws"] += 2
        iostats.gl_draw(2)

    def _tile_plan(self, visible: np.ndarray, invisible: np.ndarray
                   ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """GPU-driven, per finest tile: the visible and invisible pairs over it (copied onto the
        finest tiles), as (node, tile, count slot). A tile with more than `lca_pairs` pairs in all (or
        `lca_subtrees` visible ones) would test every pair's box per ray (incoherent rays: more box tests
        than one
        full traversal); it traverses the lowest common ancestor of all its pairs once instead (the
        front is a cut of the BVH, so that subtree holds all of them: exact), and its invisible
        pairs are neither queried nor counted (they keep their state, see _refine)."""
        f, nt = self.front, self.nt
        level = f.max_level
        n = 1 << level
        nv = len(visible)

        def copies(pairs: np.ndarray, slot0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            nd, _, tx, ty, sl = to_finest_tiles(
                f.node[pairs].astype(np.int64), f.level[pairs].astype(np.int64), f.tx[pairs].astype(np.int64),
                f.ty[pairs].astype(np.int64), slot0 + np.arange(len(pairs), dtype=np.int64), level)
            return nd, ty * n + tx, sl

        vn, vt, vs = copies(visible, 0)
        inn, it, isl = copies(invisible, nv)
        heavy = self._heavy_tiles(np.bincount(vt, minlength=n * n), np.bincount(it, minlength=n * n))
        hv, hi = heavy[vt], heavy[it]
        tiles = np.concatenate([vt[hv], it[hi]])
        nodes = np.concatenate([vn[hv], inn[hi]])
        o = np.argsort(tiles, kind="stable")
        tiles, nodes = tiles[o], nodes[o]
        starts = np.flatnonzero(np.r_[True, tiles[1:] != tiles[:-1]]) if len(tiles) else np.zeros(0, np.int64)
        lca = nt.group_lca(nodes, starts)
        self.lca_pairs = vs[hv]
        self.stats["lca_tiles"] += len(starts)
        dropped = np.ones(len(invisible), bool)
        dropped[isl[~hi] - nv] = False
        self.untested = invisible[dropped]
        vis = (np.concatenate([vn[~hv], lca]), np.concatenate([vt[~hv], tiles[starts]]),
               np.concatenate([vs[~hv], np.full(len(starts), -1, np.int64)]))
        return vis, (inn[~hi], it[~hi], isl[~hi])

    def _draw_finest(self, nd: np.ndarray, tile: np.ndarray, sl: np.ndarray) -> None:
        """GPU-driven: intersect items (node, finest tile, count slot) in one instanced draw: one
        record per finest tile (more where a tile has more than max_batch items)."""
        if len(nd) == 0:
            return
        f = self.front
        level = f.max_level
        n = 1 << level
        self.stats["subtrees_scheduled"] += len(nd)
        o = np.argsort(tile, kind="stable")
        nd, tile, sl = nd[o], tile[o], sl[o]
        starts = np.flatnonzero(np.r_[True, tile[1:] != tile[:-1]])
        ends = np.r_[starts[1:], len(nd)]
        t = tile[starts]
        rects = tile_rects(np.full(len(t), level), t % n, t // n, self.size)
        order = self.p.gap_order and self.p.gap_order_visible and not self.any_hit
        self._draw_batches(nd, sl, rects, starts, ends, t if order else None)

    def _refine(self, visible: np.ndarray, invisible: np.ndarray, cnt: np.ndarray) -> None:
        """Apply this pass's counts to the front (for the next frame): an invisible pair that rays
        entered becomes visible (terminated) or is split (its children are tested next frame);
        culled pairs age; a visible leaf whose re-query is due and that no ray entered (its own
        count, or a lowest common ancestor standing for it: then it is left visible) becomes
        invisible."""
        f, p, thr = self.front, self.p, self.threshold
        nv = len(visible)
        cv, ci = cnt[:nv], cnt[nv:]
        seen = ci > thr
        wave = invisible[seen]
        f.pixels[wave] = ci[seen]
        unseen = invisible[~seen]
        if self.untested is not None and len(self.untested):
            unseen = unseen[~np.isin(unseen, self.untested)]  # not queried (LCA tiles): not aged
        f.age[unseen] += 1
        self.stats["newly_visible_queries"] += int(seen.sum())
        if nv:
            due = f.requery_due(visible, self.frame_number())
            self.stats["requeries"] = int(due.sum())
            gone = due & (cv <= thr) & ~self.lca_covered(visible)
            f.state[visible[gone]] = INVISIBLE
            f.age[visible[due]] = 0
            f.pixels[visible[due]] = cv[due]
        if len(wave):
            term, obj, _ = f.classify(wave, self.nt, self.t_q, p.max_subtree_height, self.tri_bound)
            f.state[wave[term]] = VISIBLE
            split = wave[~term]
            if len(split):
                f.subdivide(split, obj[~term], self.nt)

    def lca_covered(self, visible: np.ndarray) -> np.ndarray:
        """Visible pairs drawn through a lowest common ancestor this pass (their counts are not theirs)."""
        out = np.zeros(len(visible), bool)
        if self.lca_pairs is not None:
            out[self.lca_pairs] = True
        return out
