"""chcrt, a pass on a host front with its queries read back within the pass (Algorithm 1 as the paper
runs it: a front's first passes, or gpu_driven=0): mixed into ChcrtPass (chcrt_pass.py), whose state
and shared steps it uses."""

from __future__ import annotations

import moderngl
import numpy as np

from viewer import iostats
from viewer.backends.chcrt.chcrt_front import INVISIBLE, VISIBLE, NodeTables, PairFront
from viewer.backends.chcrt.chcrt_layout import DRAW_DTYPE, ITEM_DTYPE
from viewer.effects import RayType
from viewer.gl import io as glio


def _clip_rects(rects: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Rects (x, y, w, h) cut to clip boxes (x0, y0, x1, y1, ends exclusive); empty ones get w = h = 0."""
    x0 = np.maximum(rects[:, 0], clip[:, 0])
    y0 = np.maximum(rects[:, 1], clip[:, 1])
    w = np.minimum(rects[:, 0] + rects[:, 2], clip[:, 2]) - x0
    h = np.minimum(rects[:, 1] + rects[:, 3], clip[:, 3]) - y0
    empty = (w <= 0) | (h <= 0)
    return np.stack([x0, y0, np.where(empty, 0, w), np.where(empty, 0, h)], 1)


def _union(bounds: np.ndarray) -> np.ndarray:
    """(n, 2, 4) per-box bounds -> (n, 4) bounds of both (an empty one has x0 > x1, y0 > y1)."""
    return np.concatenate([bounds[:, :, :2].min(1), bounds[:, :, 2:].max(1)], 1)


def _bounds_of_parents(split: np.ndarray, bounds: np.ndarray, children: np.ndarray, f: PairFront,
                       nt: NodeTables) -> np.ndarray:
    """Per child pair, where its query can pass: the parent's (`split`, per-box query bounds
    `bounds`) passing bounds of the child's node box for an object-space child (the parent's query
    drew its two children's boxes, left first), of both boxes for a child tile."""
    if len(children) == 0:
        return np.zeros((0, 4), np.int64)
    parents = f.parent[children]
    order = np.argsort(split)
    b = bounds[order[np.searchsorted(split[order], parents)]]
    out = _union(b)
    pn, cn = f.node[parents], f.node[children]
    obj = cn != pn
    box = np.where(cn == nt.left[pn], 0, 1)
    out[obj] = b[obj, box[obj]]
    return out


class SyncSteps:
    """Algorithm 1 with waves of queries read back within the pass."""

    def _run_queries(self, groups: list[np.ndarray], clip: np.ndarray | None = None) -> np.ndarray:
        """One query per group of pairs (all pairs of a group share a tile); returns samples passed.
        `clip` (per group x0, y0, x1, y1, ends exclusive): only these pixels of the tile can pass
        (an ancestor's passing bounds); a query left with no pixel is answered 0 without a draw.
        The passing pixels' bounds of each query are left in self.bounds, (nq, 2, 4): those of its
        first box, then of all its other boxes (the whole clipped rect for both where the mode does
        not measure them).

        All queries are issued first, then all results are read (one wait per wave)."""
        nq = len(groups)
        if nq == 0:
            self.bounds = np.zeros((0, 2, 4), np.int64)
            return np.zeros(0, np.int64)
        f, nt = self.front, self.nt
        sizes = np.array([len(g) for g in groups])
        pairs = np.concatenate(groups)
        owner, bmin, bmax = nt.query_boxes(f.node[pairs])
        group_of_pair = np.repeat(np.arange(nq), sizes)
        gbox = group_of_pair[owner]
        nbox = np.bincount(gbox, minlength=nq)
        base = np.cumsum(nbox) - nbox
        items = np.zeros(len(owner), ITEM_DTYPE)
        items["bmin"] = bmin
        items["bmax"] = bmax
        items["id"] = f.node[pairs][owner]
        self.be.items.upload(items)
        self.be.bind_items(self.be.items.buf)
        first = np.cumsum(sizes) - sizes
        rects = f.rects(pairs[first]).astype(np.int64)
        if clip is not None:
            rects = _clip_rects(rects, clip)
        live = (rects[:, 2] > 0) & (rects[:, 3] > 0)
        self.stats["query_pixels"] += int((rects[:, 2] * rects[:, 3]).sum())
        self.stats["queries"] += int(live.sum())
        whole = np.stack([rects[:, 0], rects[:, 1], rects[:, 0] + rects[:, 2], rects[:, 1] + rects[:, 3]], 1)
        self.bounds = np.repeat(whole[:, None, :], 2, 1)
        if self.be.batched:
            out = self._queries_batched(rects, base, nbox, live)
        else:
            out = self._queries_hw(rects, base, nbox, live)
        self._read_ray_count()
        return out

    def _queries_batched(self, rects: np.ndarray, base: np.ndarray, nbox: np.ndarray,
                         live: np.ndarray) -> np.ndarray:
        """All queries in one instanced draw; results from one buffer read."""
        nq = len(rects)
        recs = np.zeros(nq, DRAW_DTYPE)
        recs["rect"] = rects
        recs["info"][:, 0] = base
        recs["info"][:, 1] = nbox
        recs["info"][:, 2] = np.arange(nq)
        recs = recs[live]
        self.be.draws.upload(recs)
        init = np.zeros(9 * nq, np.uint32)  # counts, then per query and box slot the passing bounds
        init[nq:].reshape(nq, 2, 4)[:, :, :2] = 0xFFFFFFFF  # (min x, min y, max x, max y)
        self.be.query_counts.upload(init)
        prog = self.be.prog_query_b
        prog["countOverdraw"] = int(self.overlays)
        prog["boundsBase"] = nq
        prog["raySize"] = tuple(self.size)
        fbo = self.tg.query_fbo
        fbo.use()
        fbo.scissor = None
        self.ctx.disable(moderngl.DEPTH_TEST)
        if len(recs):
            self.be.vao_query_b.render(moderngl.TRIANGLES, vertices=6, instances=len(recs))
            self.stats["draws"] += 1
            iostats.gl_draw()
        raw = np.frombuffer(glio.read(self.be.query_counts.buf, size=36 * nq),
                            np.uint32).astype(np.int64)
        out = raw[:nq]
        b = raw[nq:].reshape(nq, 2, 4).copy()
        b[:, :, 2:] += 1  # ends exclusive; a box no pixel passed keeps x0 > x1: empty
        passed = out > 0
        self.bounds[passed] = b[passed]
        self.ctx.enable(moderngl.DEPTH_TEST)
        return out

    def _queries_hw(self, rects: np.ndarray, base: np.ndarray, nbox: np.ndarray, live: np.ndarray) -> np.ndarray:
        """The paper's way: one scissored draw inside one occlusion query object per query."""
        prog = self.be.prog_query
        prog["countOverdraw"] = int(self.overlays)
        fbo = self.tg.query_fbo
        fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        u_base, u_count = prog["itemBase"], prog["itemCount"]
        render = self.be.quad.render
        used = []
        for i, (x, y, w, h) in enumerate(rects.tolist()):
            if not live[i]:
                used.append(None)
                continue
            fbo.scissor = (x, y, w, h)
            u_base.value = int(base[i])
            u_count.value = int(nbox[i])
            q = self.be.query(i)
            with q:
                render(prog)
            used.append(q)
        n = int(live.sum())
        self.stats["draws"] += n  # (the scissored quads count themselves, viewer.gl.io)
        iostats.gl_query(n)
        with iostats.timed_sync():  # the first result waits for the draws; the others are then ready
            out = np.array([q.samples if q is not None else 0 for q in used], np.int64)
        iostats.sync(max(n - 1, 0))  # one result read per query object
        iostats.to_host(8 * n)
        return out

    def _intersect(self, pairs: np.ndarray) -> None:
        """Intersect scheduled pairs. Out-of-core (paper 5.4): pairs whose subtree is cached first,
        then the others after their upload, in chunks that never overwrite a subtree still to be drawn."""
        cache = self.be.cache
        if cache is None or len(pairs) == 0:
            self._draw_subtrees(pairs)
            return
        nd = self.front.node[pairs]
        hit = cache.cached(nd)
        cache.t.hits += len(np.unique(nd[hit]))
        self._draw_subtrees(pairs[hit])
        rest = pairs[~hit]
        if len(rest) == 0:
            return
        rest_nd = nd[~hit]
        chunk: list[int] = []
        for n in np.unique(rest_nd).tolist():
            if chunk and not set(cache.evicts(n)).isdisjoint(chunk):
                self._draw_subtrees(rest[np.isin(rest_nd, chunk)])
                chunk = []
            cache.upload(n)
            chunk.append(n)
        self._draw_subtrees(rest[np.isin(rest_nd, chunk)])

    def _run_sync(self) -> None:
        """Algorithm 1 with query results read back within the pass (waves of queries)."""
        be, f, p = self.be, self.front, self.p
        prof = be.bc.profiler
        thr = self.threshold
        with prof.phase("chc:1-intersect-visible"):
            self._bind()
            self._init()
            if p.front_to_back and self.ray_type in (RayType.PRIMARY, RayType.SHADOW, RayType.SOFT):
                self._gather()
            visible = f.leaves(VISIBLE)
            self._intersect(visible)
            self.stats["phase1_subtrees"] = len(visible)
            self._sync()

        with prof.phase("chc:2-queries"):
            invisible = f.leaves(INVISIBLE)
            groups = f.multi_query_groups(invisible, p.max_multi)
            multi = [len(g) > 1 for g in groups]
            due = visible[f.requery_due(visible, self.frame_number())] if len(visible) else visible
            groups += [due[i:i + 1] for i in range(len(due))]
            self.stats["requeries"] = len(due)
            multi += [False] * len(due)
            res = self._run_queries(groups)
            qb = self.bounds
            n_inv_groups = len(groups) - len(due)
            became_visible = []
            retry: list[np.ndarray] = []
            wave_b: list[np.ndarray] = []  # passing bounds of each pair of `wave`: its children query within them
            retry_b: list[np.ndarray] = []  # a failed multi-query's bounds: its pairs pass only there
            for i in range(n_inv_groups):
                g = groups[i]
                if multi[i]:
                    self.stats["multi_queries"] += 1
                    if res[i] > thr:
                        self.stats["failed_multi_queries"] += 1
                        retry.append(g)
                        retry_b.append(np.repeat(_union(qb[i:i + 1]), len(g), 0))
                elif res[i] > thr:
                    became_visible.append(g)
                    wave_b.append(qb[i:i + 1])
                    f.pixels[g] = res[i]
                if res[i] <= thr:
                    f.age[g] += 1
            if len(due):
                rq = res[n_inv_groups:]
                f.state[due[rq <= thr]] = INVISIBLE
                f.age[due] = 0
                f.pixels[due] = rq
            wave = np.concatenate(became_visible) if became_visible else np.zeros(0, np.int64)
            wbounds = np.concatenate(wave_b) if wave_b else np.zeros((0, 2, 4), np.int64)
            pending = np.concatenate(retry) if retry else np.zeros(0, np.int64)
            pclip = np.concatenate(retry_b) if retry_b else np.zeros((0, 4), np.int64)
            self._sync()

        with prof.phase("chc:3-traversal"):
            scheduled: list[np.ndarray] = []
            n_sched = 0
            full = False  # cold_full_bvh: the refinement stopped, every ray takes the full traversal
            self.refine_from = self.stats["query_pixels"]  # the budget counts the refinement's queries
            while True:
                if len(wave):
                    term, obj, _ = f.classify(wave, self.nt, self.t_q, p.max_subtree_height,
                                              self.tri_bound)
                    done = wave[term]
                    f.state[done] = VISIBLE
                    if len(done):
                        scheduled.append(done)
                        n_sched += len(done)
                    split = wave[~term]
                    children = f.subdivide(split, obj[~term], self.nt) if len(split) else split
                    pending = np.concatenate([pending, children])
                    pclip = np.concatenate([pclip, _bounds_of_parents(split, wbounds[~term], children, f, self.nt)])
                    wave = np.zeros(0, np.int64)
                if n_sched >= p.schedule_batch:
                    self._intersect(np.concatenate(scheduled))
                    scheduled, n_sched = [], 0
                if len(pending) == 0:
                    break
                why = self._incoherent()
                if why:
                    # this pass traces the whole BVH; a front stopped by its budget goes on refining
                    # in its next pass (cold_passes), an incoherent one stays on full traversals
                    full = True
                    f.cold_stops += why == "budget"
                    f.full_bvh = why == "incoherent" or f.cold_stops >= p.cold_passes
                    break
                self.stats["query_waves"] += 1
                res = self._run_queries([np.array([i]) for i in pending], pclip)
                vis = res > thr
                f.pixels[pending] = res
                f.age[pending[~vis]] += 1
                wave = pending[vis]
                wbounds = self.bounds[vis]
                pending = np.zeros(0, np.int64)
                pclip = np.zeros((0, 4), np.int64)
            self._sync()

        f.cold = full and not f.full_bvh  # refined to the end (or given up): later passes are GPU-driven
        with prof.phase("chc:4-final-intersect"):
            if full:
                # the hits found so far are replaced by the full traversal's (exact); the front keeps
                # what was refined, its untested pairs invisible (the next pass queries them, or, with
                # full_bvh, goes full-BVH too)
                self.be.finisher.run(self.rays, self.pinfo, self.hits)
                self.stats["full_bvh_passes"] = 1
                self.stats["draws"] += 1
            elif scheduled:
                self._intersect(np.concatenate(scheduled))
            self._read_ray_count()
            self._sync()

    def _incoherent(self) -> str | None:
        """cold_full_bvh, before each wave of a front's synchronous refinement (the GPU-driven pass
        follows it): "incoherent" when the GPU-driven pass would trace the whole BVH with the front as
        it stands (at least full_bvh_fraction of the finest tiles over lca_pairs pairs or lca_subtrees
        visible ones, as in _tile_plan, chcrt_pass_gpu.py); when this pass's refinement has cost more than a full
        traversal (cold_query_budget; the refinement's queries only, so that a pass that goes on
        with a front stopped before gets as far again whatever its re-queries of the known pairs
        cost), "budget" if it cost at most cold_wave_queries per ray and wave (coherent rays in a
        deep BVH: the front's next pass goes on), else "incoherent"; None: refine on."""
        p, f = self.p, self.front
        if not (p.cold_full_bvh and self.be.gpu_driven and f.cold and p.lca_invisible and p.merge_tiles
                and p.full_bvh_fraction > 0 and (p.lca_pairs > 0 or p.lca_subtrees > 0)):
            return None
        vis, inv = f.leaves(VISIBLE), f.leaves(INVISIBLE)
        heavy = self._heavy_tiles(self._per_finest_tile(vis), self._per_finest_tile(inv))
        if heavy.mean() >= p.full_bvh_fraction:
            return "incoherent"
        self._read_ray_count()
        spent = self.stats["query_pixels"] - self.refine_from
        rays = max(self.stats["rays"], 1)
        if p.cold_query_budget > 0 and spent > p.cold_query_budget * rays:
            waves = max(self.stats["query_waves"], 1)
            return "budget" if spent <= p.cold_wave_queries * rays * waves else "incoherent"
        return None

    def _per_finest_tile(self, pairs: np.ndarray) -> np.ndarray:
        """How many of `pairs` cover each finest tile (2^L x 2^L counts; a pair of a coarser tile
        covers all finest tiles inside it)."""
        f = self.front
        top = f.max_level
        out = np.zeros((1 << top, 1 << top), np.int64)
        lvl = f.level[pairs].astype(np.int64)
        for L in np.unique(lvl).tolist():
            sel = pairs[lvl == L]
            m = 1 << L
            c = np.bincount(f.ty[sel].astype(np.int64) * m + f.tx[sel].astype(np.int64), minlength=m * m)
            s = 1 << (top - L)
            out += np.repeat(np.repeat(c.reshape(m, m), s, axis=0), s, axis=1)
        return out
