"""CHC+RT out-of-core ray tracing (paper section 5.4): a GPU cache of scheduled BVH subtrees.

With a GPU memory budget, the intersection shaders read BVH nodes and triangles only from two
fixed-size GPU buffers (the cache), not from the scene's buffers. The top of the BVH, the nodes
whose subtree exceeds the scheduling limits (`max_subtree_tris`, `max_subtree_height`) and can
therefore never be intersected as a whole, is what queries and the split rule need: its boxes stay
resident (NodeTables; counted against the budget at GPU node size). The rest of the budget is the
cache, split between a node buffer and a triangle buffer in the scene's own BVH : geometry ratio.

A scheduled subtree (an inner node or a BVH leaf) is one cache *entry*: its inner nodes, root first,
re-addressed into the node buffer (child references and leaf triangle references relocated), and
its contiguous triangle range in the triangle buffer. Each buffer is written round robin: the
next entry goes right after the previous one, or to the start when it does not fit before the
end; entries it overwrites are evicted from the cache (out-of-core again). The triangles keep
their leaf-order slot in the `id` field, which the shader reports as the hit (CHC_OOC).

Pure NumPy host side plus the two GL buffers; the draw scheduling (cached subtrees first, the
rest after their upload) is in chcrt_pass.ChcrtPass.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import moderngl
import numpy as np

from viewer import iostats
from viewer.accel.bvh import GPU_NODE_DTYPE, GPU_TRI_DTYPE, gpu_triangles
from viewer.errors import RtwalkError

NODE_BYTES = GPU_NODE_DTYPE.itemsize
TRI_BYTES = GPU_TRI_DTYPE.itemsize
MB = 1 << 20


@dataclass
class Entry:
    node: int  # canonical BVH node
    node_base: int  # first slot in the node buffer (root there); unused for a BVH leaf
    n_nodes: int
    tri_base: int
    n_tris: int
    live: bool = True
    seq: int = 0  # upload number (identifies the entry in SubtreeCache.in_flight)


class RingAllocator:
    """Round-robin placement in a buffer of `capacity` slots; returns the entries it overwrites."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.ptr = 0
        self.fifo: deque[tuple[int, Entry]] = deque()  # (start, entry) in write order

    def place(self, size: int, entry: Entry) -> tuple[int, list[Entry]]:
        if size > self.capacity:
            raise ValueError("entry larger than the buffer")
        evicted = []
        if self.ptr + size > self.capacity:  # wrap: the tail is overwritten by nothing but is freed
            while self.fifo and self.fifo[0][0] >= self.ptr:
                evicted.append(self.fifo.popleft()[1])
            self.ptr = 0
        # the oldest entries lie right after ptr (previous lap); those starting in [ptr, ptr+size) go
        while self.fifo and self.ptr <= self.fifo[0][0] < self.ptr + size:
            evicted.append(self.fifo.popleft()[1])
        start = self.ptr
        if size > 0:
            self.fifo.append((start, entry))
        self.ptr += size
        return start, evicted

    def would_evict(self, size: int) -> list[Entry]:
        """The entries place(size) would overwrite (nothing changes)."""
        ptr, out = self.ptr, []
        it = iter(self.fifo)
        nxt = next(it, None)
        if ptr + size > self.capacity:
            while nxt is not None and nxt[0] >= ptr:
                out.append(nxt[1])
                nxt = next(it, None)
            ptr = 0
        while nxt is not None and ptr <= nxt[0] < ptr + size:
            out.append(nxt[1])
            nxt = next(it, None)
        return out


@dataclass
class Transfer:
    """Per-pass cache counters."""

    uploads: int = 0
    hits: int = 0
    evictions: int = 0
    syncs: int = 0  # uploads that waited for the draws reading what they overwrite
    bvh_bytes: int = 0
    geom_bytes: int = 0


@dataclass
class CachePlan:
    """How a budget splits (pure NumPy, no GL): the resident BVH top and the two cache buffers."""

    triangles: int
    scene_bvh_bytes: int  # all GPU inner nodes
    scene_geom_bytes: int  # all GPU triangles
    budget_bytes: int
    top_nodes: int
    resident_bytes: int
    node_cap: int  # cache slots
    tri_cap: int
    need_nodes: int  # the largest schedulable subtree
    need_tris: int

    @property
    def scene_bytes(self) -> int:
        return self.scene_bvh_bytes + self.scene_geom_bytes

    @property
    def cache_bytes(self) -> int:
        return self.node_cap * NODE_BYTES + self.tri_cap * TRI_BYTES

    @property
    def in_core_fraction(self) -> float:
        """Share of the scene's ray-tracing data (BVH + triangles) the GPU holds at once."""
        return min(1.0, (self.resident_bytes + self.cache_bytes) / max(self.scene_bytes, 1))

    @staticmethod
    def scene_bytes_of(bvh) -> int:
        n_inner = max(int((np.asarray(bvh.node_left) >= 0).sum()), 1)
        return n_inner * NODE_BYTES + int(np.asarray(bvh.node_count)[0]) * TRI_BYTES

    @staticmethod
    def of(bvh, budget_bytes: int, max_tris: int, max_height: int, n_inner: np.ndarray | None = None) -> CachePlan:
        left = np.asarray(bvh.node_left, np.int64)
        is_leaf = left < 0
        count = np.asarray(bvh.node_count, np.int64)
        if n_inner is None:
            n_inner = inner_counts(bvh)
        schedulable = (count <= max_tris) & (np.asarray(bvh.node_height, np.int64) <= max_height)
        top = int((~schedulable & ~is_leaf).sum())  # never scheduled whole: stays resident
        bvh_bytes = max(int((~is_leaf).sum()), 1) * NODE_BYTES
        geom_bytes = int(count[0]) * TRI_BYTES
        frac = bvh_bytes / max(bvh_bytes + geom_bytes, 1)
        cache = int(budget_bytes) - top * NODE_BYTES
        return CachePlan(int(count[0]), bvh_bytes, geom_bytes, int(budget_bytes), top, top * NODE_BYTES,
                         max(int(cache * frac) // NODE_BYTES, 0), max(int(cache * (1 - frac)) // TRI_BYTES, 0),
                         int(n_inner[schedulable].max(initial=0)), int(count[schedulable].max(initial=1)))

    def check(self) -> None:
        if self.node_cap < self.need_nodes or self.tri_cap < self.need_tris or self.node_cap < 1:
            frac = self.scene_bvh_bytes / max(self.scene_bytes, 1)
            need = self.resident_bytes + max(self.need_nodes * NODE_BYTES / frac,
                                             self.need_tris * TRI_BYTES / (1 - frac))
            raise RtwalkError(f"chcrt: gpu budget of {self.budget_bytes / MB:.3f} MB is too small: the BVH top "
                              f"({self.resident_bytes / MB:.3f} MB) and one subtree of up to {self.need_tris} "
                              f"triangles need about {need / MB:.3f} MB (lower max_subtree_tris or raise the budget)")


def inner_counts(bvh) -> np.ndarray:
    """Inner nodes per canonical subtree: leaves - 1 (binary tree; leaf triangle ranges are
    contiguous and non-empty, so a subtree's leaves are those whose first slot lies in its range)."""
    first = np.asarray(bvh.node_first, np.int64)
    count = np.asarray(bvh.node_count, np.int64)
    is_leaf = np.asarray(bvh.node_left) < 0
    lf = np.sort(first[is_leaf])
    n_leaves = np.searchsorted(lf, first + count) - np.searchsorted(lf, first)
    return np.where(is_leaf, 0, n_leaves - 1)


class SubtreeCache:
    """Scheduled subtrees resident on the GPU within a memory budget (see the module docstring)."""

    def __init__(self, ctx: moderngl.Context, bvh, triangles: np.ndarray, material_ids: np.ndarray,
                 budget_bytes: int, max_tris: int, max_height: int):
        left = np.asarray(bvh.node_left, np.int64)
        is_leaf = left < 0
        first = np.asarray(bvh.node_first, np.int64)
        count = np.asarray(bvh.node_count, np.int64)
        self.first, self.count, self.is_leaf = first, count, is_leaf
        self.left, self.right = left, np.asarray(bvh.node_right, np.int64)
        self.inner_index = np.asarray(bvh.inner_index_of_node(), np.int64)
        self.n_inner = inner_counts(bvh)
        self.plan = plan = CachePlan.of(bvh, budget_bytes, max_tris, max_height, self.n_inner)
        plan.check()
        # host copies of what the cache is filled from ("out of core": host memory)
        self.host_nodes = bvh.gpu_nodes()
        self.host_tris = gpu_triangles(triangles, material_ids)
        self.node_cap, self.tri_cap = plan.node_cap, plan.tri_cap
        self.nodes_buf = ctx.buffer(reserve=self.node_cap * NODE_BYTES)
        self.tris_buf = ctx.buffer(reserve=self.tri_cap * TRI_BYTES)
        self.node_ring = RingAllocator(self.node_cap)
        self.tri_ring = RingAllocator(self.tri_cap)
        self.entries: dict[int, Entry] = {}  # canonical node -> live entry
        self.in_flight: set[int] = set()  # entries (seq) read by draws issued since the last glFinish
        self.seq = 0
        self.ctx = ctx
        self.t = Transfer()

    def bind(self, nodes_binding: int, tris_binding: int) -> None:
        self.nodes_buf.bind_to_storage_buffer(nodes_binding)
        self.tris_buf.bind_to_storage_buffer(tris_binding)

    def begin_pass(self) -> None:
        self.t = Transfer()

    def cached(self, nodes: np.ndarray) -> np.ndarray:
        """bool per canonical node: its subtree is in the cache now."""
        return np.array([int(n) in self.entries for n in nodes.tolist()], bool)

    def evicts(self, node: int) -> list[int]:
        """Canonical nodes whose entries uploading `node` now would overwrite."""
        out = self.node_ring.would_evict(int(self.n_inner[node])) + self.tri_ring.would_evict(int(self.count[node]))
        return [e.node for e in out if e.live]

    def upload(self, node: int) -> Entry:
        """Place subtree `node` in both rings (evicting what it overwrites) and write its data."""
        node = int(node)
        n_nodes, n_tris = int(self.n_inner[node]), int(self.count[node])
        self.seq += 1
        e = Entry(node, 0, n_nodes, 0, n_tris, seq=self.seq)
        e.node_base, ev1 = self.node_ring.place(n_nodes, e)
        e.tri_base, ev2 = self.tri_ring.place(n_tris, e)
        if not self.in_flight.isdisjoint(old.seq for old in ev1 + ev2):
            # llvmpipe does not order glBufferSubData after queued draws that read the buffer as an
            # SSBO: wait for them before overwriting what they read
            with iostats.timed_sync():
                self.ctx.finish()
            self.in_flight.clear()
            self.t.syncs += 1
        for old in ev1 + ev2:
            if old.live:
                old.live = False
                del self.entries[old.node]
                self.t.evictions += 1
        self.entries[node] = e
        f = int(self.first[node])
        tris = self.host_tris[f:f + n_tris]
        self.tris_buf.write(tris.tobytes(), offset=e.tri_base * TRI_BYTES)
        iostats.to_device(tris.nbytes)
        if n_nodes:
            sub = self._subtree_inner(node)  # inner GPU indices, root first
            g = self.host_nodes[sub].copy()
            local = np.full(len(self.host_nodes), -1, np.int64) if n_nodes > 4096 else None
            for side in ("left", "right"):
                ref = g[side].astype(np.int64)
                inner = ref >= 0
                if local is not None:
                    local[sub] = np.arange(n_nodes)
                    idx = local[ref[inner]]
                else:
                    order = np.argsort(sub)
                    idx = order[np.searchsorted(sub, ref[inner], sorter=order)]
                ref[inner] = e.node_base + idx
                ref[~inner] = ~(e.tri_base + (~ref[~inner] - f))
                g[side] = ref.astype(np.int32)
            self.nodes_buf.write(g.tobytes(), offset=e.node_base * NODE_BYTES)
            iostats.to_device(g.nbytes)
        self.t.uploads += 1
        self.t.bvh_bytes += n_nodes * NODE_BYTES
        self.t.geom_bytes += n_tris * TRI_BYTES
        return e

    def _subtree_inner(self, node: int) -> np.ndarray:
        """GPU inner-node indices of the subtree under canonical `node`, root first (level order)."""
        out = []
        front = np.array([node], np.int64)
        while len(front):
            inner = front[~self.is_leaf[front]]
            out.append(self.inner_index[inner])
            front = np.concatenate([self.left[inner], self.right[inner]])
        return np.concatenate(out)

    def item_refs(self, nodes: np.ndarray) -> np.ndarray:
        """Cache references of cached subtrees (node slot of an inner root, triangle slot of a BVH
        leaf), for a draw about to be issued: their entries are then in flight."""
        ents = [self.entries[int(n)] for n in nodes.tolist()]
        self.in_flight.update(e.seq for e in ents)
        return np.array([e.tri_base if e.n_nodes == 0 else e.node_base for e in ents], np.int32)

    def release(self) -> None:
        self.nodes_buf.release()
        self.tris_buf.release()
