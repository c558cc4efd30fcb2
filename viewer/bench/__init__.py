"""Benchmarks: a backend-neutral harness and what is built on it.

- harness: replay of a recording, consecutive frames, warm-up and reset, interleaved configurations
- estimate: the up-front time estimate (a per-ray cost model per backend)
- report / plots: JSON + Markdown writing and the one plotting helper every report uses
- replay: `rtwalk bench` (one configuration over a recording, error against Embree)
- chcrt: `rtwalk bench-chcrt` (the CHC+RT paper's tables)
- gl_micro: synthetic per-draw / per-query GL costs (the overhead study)
- trace_vs_embree: `rtwalk bench-trace`; cl_primitives: `rtwalk bench-cl`

Import each name from its module; this package re-exports nothing.
"""
