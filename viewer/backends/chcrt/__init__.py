"""chcrt: CHC+RT (coherent hierarchical culling for ray tracing), a backend folder with its code and
its shaders (chc_*, loaded through this folder's search path):
- chcrt.py: the backend (the method in its docstring, programs, per-front state, trace());
- chcrt_params.py: its parameters; chcrt_layout.py: what the shaders and passes share (bindings,
  record dtypes, buffer sizes);
- chcrt_pass.py: one pass and its shared steps, with its three modes: chcrt_pass_sync.py (queries
  read back within the pass), chcrt_pass_gpu.py (GPU-driven, front on the host),
  chcrt_pass_device.py (GPU-driven, front on the device);
- chcrt_front.py: the query-pair hierarchy; chcrt_devfront.py: its device-resident copy and the
  dispatches that plan and refine it; chcrt_cache.py: the out-of-core subtree cache."""

from viewer.backends.chcrt.chcrt import ChcrtBackend
from viewer.backends.chcrt.chcrt_params import MAX_LEAF_CACHE, ChcrtParams

__all__ = ["MAX_LEAF_CACHE", "ChcrtBackend", "ChcrtParams"]
