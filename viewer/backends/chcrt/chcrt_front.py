"""CHC+RT query-pair hierarchy (pure NumPy; no GL): tiles, split rule, fronts.

A query pair is (screen tile, BVH node). The ray hierarchy is a quadtree over the ray batch:
the tile (level L, x, y) covers pixels [x*W >> L, (x+1)*W >> L) x [y*H >> L, (y+1)*H >> L).
The object hierarchy is the canonical BVH (viewer.accel.bvh.BVH node indices).

Screen tiles are the generic quadtree of viewer.screen_tiles (tile_rects, max_tile_level).

The pair hierarchy is kept between frames (one per ray type / sample / light) as flat arrays.
Its leaves form the *front*: every leaf is either

* INVISIBLE: culled by its last query (or a merged parent of culled pairs), or
* VISIBLE: a terminated pair whose subtree is intersected for the tile's rays every frame.

Inner pairs (INNER) were visible and refined; their children are stored contiguously (2 after an
object-space split, 4 after a ray-space split). The leaves of the hierarchy partition
(screen x scene), which is what makes culling exact: every (ray, triangle) combination belongs
to exactly one leaf pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from viewer.screen_tiles import tile_rects

INVISIBLE = 0
VISIBLE = 1
INNER = 2
DEAD = 3


@dataclass
class NodeTables:
    """Per canonical BVH node: what the split rule, the queries and the intersection need."""

    left: np.ndarray  # int32
    right: np.ndarray  # int32
    is_leaf: np.ndarray  # bool
    height: np.ndarray  # int32
    count: np.ndarray  # int32 triangles in the subtree
    area_ratio: np.ndarray  # float64 surface area / root surface area
    box_min: np.ndarray  # float32 (M, 3)
    box_max: np.ndarray  # float32 (M, 3)
    gpu_ref: np.ndarray  # int32: GPU inner-node index (inner) or first triangle slot (leaf)
    gpu_count: np.ndarray  # int32: 0 for inner nodes, triangle count for leaves
    parent: np.ndarray  # int32, -1 for the root
    depth: np.ndarray  # int32, 0 for the root
    first: np.ndarray  # int32: first triangle slot (leaf order) of the subtree; [first, first + count) nest
    area32: np.ndarray  # float32 area_ratio: what the split rule compares, on the host and the device alike

    @staticmethod
    def from_bvh(bvh) -> NodeTables:
        lo = bvh.node_min.astype(np.float64)
        ext = np.maximum(bvh.node_max.astype(np.float64) - lo, 0.0)
        area = ext[:, 0] * ext[:, 1] + ext[:, 1] * ext[:, 2] + ext[:, 2] * ext[:, 0]
        root = area[0] if area[0] > 0 else 1.0
        is_leaf = bvh.node_left < 0
        inner_idx = bvh.inner_index_of_node()
        gpu_ref = np.where(is_leaf, bvh.node_first, inner_idx).astype(np.int32)
        gpu_count = np.where(is_leaf, bvh.node_count, 0).astype(np.int32)
        left = bvh.node_left.astype(np.int32)
        right = bvh.node_right.astype(np.int32)
        parent = np.full(len(left), -1, np.int32)
        inner = np.flatnonzero(left >= 0)
        parent[left[inner]] = inner
        parent[right[inner]] = inner
        depth = np.zeros(len(left), np.int32)
        level = np.array([0])
        d = 0
        while len(level):  # breadth first: one NumPy step per tree level
            depth[level] = d
            kids = level[left[level] >= 0]
            level = np.concatenate([left[kids], right[kids]])
            d += 1
        return NodeTables(left, right, is_leaf, bvh.node_height.astype(np.int32),
                          bvh.node_count.astype(np.int32), area / root,
                          np.ascontiguousarray(bvh.node_min, np.float32),
                          np.ascontiguousarray(bvh.node_max, np.float32), gpu_ref, gpu_count, parent, depth,
                          np.asarray(bvh.node_first, np.int32), (area / root).astype(np.float32))

    def group_lca(self, nodes: np.ndarray, starts: np.ndarray) -> np.ndarray:
        """Lowest common ancestor of each group of `nodes` (groups are the runs that begin at
        `starts`): every node is lifted to its group's shallowest depth, then all are lifted one
        level at a time until each group agrees. Vectorised over groups: one step per tree level."""
        nodes = np.asarray(nodes, np.int64).copy()
        if len(nodes) == 0:
            return nodes
        group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(nodes)]))
        target = np.minimum.reduceat(self.depth[nodes], starts)[group]
        while True:
            deep = self.depth[nodes] > target
            if not deep.any():
                break
            nodes[deep] = self.parent[nodes[deep]]
        while True:
            lo = np.minimum.reduceat(nodes, starts)
            hi = np.maximum.reduceat(nodes, starts)
            differ = (lo != hi)[group]
            if not differ.any():
                return lo
            nodes[differ] = self.parent[nodes[differ]]

    def query_boxes(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boxes a query of `nodes` rasterises ("tighter bounds": both children of an inner node,
        the node's own box for a leaf). Returns (owner index into nodes, box min, box max)."""
        nodes = np.asarray(nodes, np.int64)
        inner = ~self.is_leaf[nodes]
        nb = np.where(inner, 2, 1)
        owner = np.repeat(np.arange(len(nodes)), nb)
        second = np.zeros(len(owner), bool)
        starts = np.cumsum(nb) - nb
        second[starts[inner] + 1] = True
        first_box = np.where(inner, self.left[nodes], nodes)
        box_node = np.where(second, self.right[nodes][owner], first_box[owner])
        return owner, self.box_min[box_node], self.box_max[box_node]


class PairFront:
    """The query-pair hierarchy of one (ray type, sample, light) for one ray-batch size."""

    def __init__(self, size: tuple[int, int], max_level: int, rng: np.random.Generator,
                 requery_interval: int):
        self.size = size
        self.max_level = max_level
        self.rng = rng
        self.requery_interval = max(int(requery_interval), 1)
        cap = 256
        self.level = np.zeros(cap, np.int8)
        self.tx = np.zeros(cap, np.int32)
        self.ty = np.zeros(cap, np.int32)
        self.node = np.zeros(cap, np.int32)
        self.parent = np.full(cap, -1, np.int32)
        self.child = np.full(cap, -1, np.int32)  # first child (children are contiguous)
        self.nchild = np.zeros(cap, np.int8)
        self.state = np.full(cap, DEAD, np.int8)
        self.offset = np.zeros(cap, np.int8)  # re-query phase of visible leaves
        self.pixels = np.zeros(cap, np.int32)  # samples passed at the last query that saw it
        self.age = np.zeros(cap, np.int16)  # consecutive passes the pair has been invisible
        self.n = 0
        self.dead = 0
        self.frames = 0  # passes traced with this front
        # the front's synchronous refinement is unfinished: its first pass, and every pass after one that
        # stopped refining on its query budget (chcrt cold_full_bvh, cold_passes), run the synchronous
        # algorithm and go on refining from where the last one stopped
        self.cold = True
        self.cold_stops = 0  # synchronous passes that stopped refining on their query budget
        # incoherent rays: a synchronous pass found them so (chcrt cold_full_bvh); every pass traces the
        # whole BVH, the front is not refined further
        self.full_bvh = False
        # the front's copy on the device once its refinement is done (chcrt_devfront.DeviceFront); the
        # arrays here are then no longer updated
        self.device: object | None = None
        self._append(np.zeros(1, np.int8), np.zeros(1, np.int32), np.zeros(1, np.int32),
                     np.zeros(1, np.int32), np.full(1, -1, np.int32))

    # -- storage ---------------------------------------------------------------------------------
    _FIELDS = ("level", "tx", "ty", "node", "parent", "child", "nchild", "state", "offset", "pixels", "age")

    def _grow(self, need: int) -> None:
        cap = len(self.level)
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in self._FIELDS:
            old = getattr(self, name)
            fill = -1 if name in ("parent", "child") else (DEAD if name == "state" else 0)
            arr = np.full(new_cap, fill, old.dtype)
            arr[: self.n] = old[: self.n]
            setattr(self, name, arr)

    def _append(self, level, tx, ty, node, parent) -> np.ndarray:
        k = len(node)
        self._grow(self.n + k)
        s = slice(self.n, self.n + k)
        self.level[s] = level
        self.tx[s] = tx
        self.ty[s] = ty
        self.node[s] = node
        self.parent[s] = parent
        self.child[s] = -1
        self.nchild[s] = 0
        self.state[s] = INVISIBLE
        self.offset[s] = self.rng.integers(0, self.requery_interval, k)
        self.pixels[s] = 0
        self.age[s] = 0
        idx = np.arange(self.n, self.n + k, dtype=np.int64)
        self.n += k
        return idx

    # -- queries about the front ----------------------------------------------------------------------
    def leaves(self, state: int) -> np.ndarray:
        return np.flatnonzero(self.state[: self.n] == state)

    def tile_key(self, idx: np.ndarray) -> np.ndarray:
        """One int64 per pair identifying its tile (level, x, y)."""
        return ((self.level[idx].astype(np.int64) << 40) | (self.tx[idx].astype(np.int64) << 20)
                | self.ty[idx].astype(np.int64))

    def rects(self, idx: np.ndarray) -> np.ndarray:
        return tile_rects(self.level[idx], self.tx[idx], self.ty[idx], self.size)

    def requery_due(self, idx: np.ndarray, frame: int) -> np.ndarray:
        return (frame + self.offset[idx].astype(np.int64)) % self.requery_interval == 0

    def multi_query_groups(self, idx: np.ndarray, max_multi: int) -> list[np.ndarray]:
        """Group invisible pairs for multi-queries as CHC++ does (Mattausch et al. 2008): pairs of
        one tile, most likely to stay invisible first; a pair invisible for i frames stays
        invisible with probability q = 0.99 - 0.7 exp(-i); a group grows while the expected
        number of pairs per query, |M| / (1 + (1 - prod q) |M|) (1 for a single query, which is
        never repeated), increases (up to max_multi)."""
        if len(idx) == 0:
            return []
        tile = self.tile_key(idx)
        q = 0.99 - 0.7 * np.exp(-self.age[idx].astype(np.float64))
        order = np.lexsort((-q, tile))
        idx, tile, q = idx[order], tile[order], q[order]
        starts = np.flatnonzero(np.r_[True, tile[1:] != tile[:-1]])
        ends = np.r_[starts[1:], len(idx)]
        groups = []
        for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
            i = s
            while i < e:
                j = min(e, i + max_multi)
                if j - i > 1:
                    k = np.arange(1, j - i + 1)
                    value = k / (1.0 + (1.0 - np.cumprod(q[i:j])) * k)
                    value[0] = 1.0  # a single query is never repeated
                    # grow while the value increases: stop before the first decrease
                    dec = np.flatnonzero(np.diff(value) < 0)
                    j = i + (int(dec[0]) + 1 if len(dec) else j - i)
                groups.append(idx[i:j])
                i = j
        return groups

    # -- refinement -----------------------------------------------------------------------------------
    def classify(self, idx: np.ndarray, nt: NodeTables, t_q: float, max_height: int,
                 max_tris: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Split decision for visible pairs: (terminate, split in object space, split the tile).

        Object space is preferred when A_node / A_root > t_q * A_tile / A_screen (the paper's
        rule). A pair terminates when the rule asks for a tile split the quadtree cannot make
        (minimum tile size reached) and the subtree is small enough (height and triangle limits);
        a subtree that is too big is split in object space even against the rule, and a BVH leaf
        that the rule would split in object space is split in ray space while the tile allows.
        """
        nd = self.node[idx]
        lvl = self.level[idx].astype(np.int64)
        leaf = nt.is_leaf[nd]
        # in float32, as chc_front_refine.comp (t_q * 4^-level is exact: a power of two)
        prefer_obj = nt.area32[nd] > np.ldexp(np.float32(t_q), -2 * lvl)
        can_ray = lvl < self.max_level
        small = (nt.height[nd] <= max_height) & (nt.count[nd] <= max_tris)
        obj = ~leaf & (prefer_obj | (~can_ray & ~small))
        ray = ~obj & can_ray
        term = ~obj & ~ray
        return term, obj, ray

    def subdivide(self, idx: np.ndarray, obj: np.ndarray, nt: NodeTables) -> np.ndarray:
        """Split pairs `idx` (object space where `obj`, else ray space); returns the new children."""
        out = []
        po = idx[obj]
        if len(po):
            nd = self.node[po]
            kids = np.stack([nt.left[nd], nt.right[nd]], axis=1).reshape(-1)
            par = np.repeat(po, 2)
            c = self._append(self.level[par], self.tx[par], self.ty[par], kids, par)
            self.child[po] = c[0::2]
            self.nchild[po] = 2
            self.state[po] = INNER
            out.append(c)
        pr = idx[~obj]
        if len(pr):
            par = np.repeat(pr, 4)
            qx = np.tile(np.array([0, 1, 0, 1], np.int32), len(pr))
            qy = np.tile(np.array([0, 0, 1, 1], np.int32), len(pr))
            c = self._append(self.level[par] + 1, 2 * self.tx[par] + qx, 2 * self.ty[par] + qy,
                             self.node[par], par)
            self.child[pr] = c[0::4]
            self.nchild[pr] = 4
            self.state[pr] = INNER
            out.append(c)
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def presplit(self, nt: NodeTables, t_q: float, max_height: int, max_tris: int, max_pairs: int) -> int:
        """A new front's first levels, split on the host by the split rule (classify) as if every pair
        were entered by rays, wave by wave while the front would stay within `max_pairs` pairs; its
        leaves stay invisible and untested (the device pass tests them: ChcrtParams.cold_start_pairs).
        Returns the waves split. Why: a device cold start refines a level a pass from its counts, and
        the first levels are the ones every view enters (the screen's coarse tiles, the tree's top)."""
        assert self.n == 1, "presplit: a new front, (screen, root)"
        wave = np.zeros(1, np.int64)
        waves = 0
        while len(wave):
            term, obj, _ = self.classify(wave, nt, t_q, max_height, max_tris)
            split, obj = wave[~term], obj[~term]
            if len(split) == 0 or self.n + int(np.where(obj, 2, 4).sum()) > max_pairs:
                break
            wave = self.subdivide(split, obj, nt)
            waves += 1
        return waves

    def pull_up(self, min_age: int = 0) -> int:
        """Merge inner pairs whose children are all invisible leaves into one invisible leaf.

        One level per call (the paper pulls invisibility up one level per frame). With `min_age`
        only children culled by at least that many queries merge (the GPU-driven pass refines a pair
        at the end of a frame and queries its fresh children in the next: they must not be merged
        back before they were queried). Returns the number of merged parents.
        """
        n = self.n
        inner = np.flatnonzero(self.state[:n] == INNER)
        if len(inner) == 0:
            return 0
        merge = []
        for k in (2, 4):
            p = inner[self.nchild[inner] == k]
            if len(p) == 0:
                continue
            kids = self.child[p][:, None] + np.arange(k)[None, :]
            ok = ((self.state[kids] == INVISIBLE) & (self.age[kids] >= min_age)).all(axis=1)
            if ok.any():
                merge.append((p[ok], kids[ok].reshape(-1)))
        total = 0
        for p, kids in merge:
            self.state[kids] = DEAD
            self.state[p] = INVISIBLE
            self.child[p] = -1
            self.nchild[p] = 0
            self.offset[p] = self.rng.integers(0, self.requery_interval, len(p))
            self.age[p] = self.age[kids].reshape(len(p), -1).min(axis=1)
            self.dead += len(kids)
            total += len(p)
        if self.dead > 1024 and self.dead > n // 2:
            self.compact()
        return total

    def compact(self) -> None:
        n = self.n
        keep = self.state[:n] != DEAD
        new_idx = np.cumsum(keep) - 1
        m = int(keep.sum())
        for name in self._FIELDS:
            arr = getattr(self, name)
            arr[:m] = arr[:n][keep]
            fill = -1 if name in ("parent", "child") else (DEAD if name == "state" else 0)
            arr[m:n] = fill
        for name in ("parent", "child"):
            arr = getattr(self, name)[:m]
            ok = arr >= 0
            arr[ok] = new_idx[arr[ok]]
        self.n = m
        self.dead = 0

    def check(self, nt: NodeTables) -> None:
        """Invariants (tests): leaves partition every inner pair, children point back."""
        n = self.n
        st = self.state[:n]
        assert st[0] != DEAD and self.parent[0] == -1
        inner = np.flatnonzero(st == INNER)
        for p in inner:
            c0, k = int(self.child[p]), int(self.nchild[p])
            kids = np.arange(c0, c0 + k)
            assert k in (2, 4) and (self.parent[kids] == p).all() and (st[kids] != DEAD).all()
            if k == 2:
                nd = self.node[p]
                assert sorted(self.node[kids]) == sorted([nt.left[nd], nt.right[nd]])
                assert (self.level[kids] == self.level[p]).all()
            else:
                assert (self.node[kids] == self.node[p]).all()
                assert (self.level[kids] == self.level[p] + 1).all()
        alive = np.flatnonzero(st != DEAD)
        nonroot = alive[alive != 0]
        assert (st[self.parent[nonroot]] == INNER).all()


def to_finest_tiles(nd: np.ndarray, lvl: np.ndarray, tx: np.ndarray, ty: np.ndarray, sl: np.ndarray,
                     top: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each (node, tile) copied onto the tiles of level `top` (default: the deepest present) that its
    tile covers (a tile of level L is exactly its four children of level L + 1)."""
    top = int(lvl.max()) if top is None else top
    sh = top - lvl
    copies = np.left_shift(1, 2 * sh)
    idx = np.repeat(np.arange(len(nd)), copies)
    k = np.arange(len(idx)) - np.repeat(np.cumsum(copies) - copies, copies)
    s = sh[idx]
    side = np.left_shift(1, s)
    return (nd[idx], np.full(len(idx), top, np.int64), (tx[idx] << s) + k % side, (ty[idx] << s) + k // side,
            sl[idx])
