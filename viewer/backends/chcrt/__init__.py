"""chcrt: CHC+RT (coherent hierarchical culling for ray tracing), a backend folder with its code
(chcrt.py: the passes; chcrt_front.py: the query-pair hierarchy; chcrt_cache.py: the out-of-core
subtree cache) and its shaders (chc_*), loaded through this folder's search path."""

from viewer.backends.chcrt.chcrt import MAX_LEAF_CACHE, ChcrtBackend, ChcrtParams

__all__ = ["MAX_LEAF_CACHE", "ChcrtBackend", "ChcrtParams"]
