"""Benchmarks: a backend-neutral harness and what is built on it.

- harness: replay of a recording, consecutive frames, warm-up and reset, interleaved configurations
- estimate: the up-front time estimate (a per-ray cost model per backend)
- report / plots: JSON + Markdown writing and the one plotting helper every report uses
- replay: `rtwalk bench` (one configuration over a recording, error against Embree)
- chcrt: `rtwalk bench-chcrt` (the CHC+RT paper's tables)
- gl_micro: synthetic per-draw / per-query GL costs (the overhead study)

The names of the former viewer/bench.py are re-exported here (`from viewer.bench import run_bench`).
"""

from viewer.bench.harness import frame_numbers, frame_row, image_error
from viewer.bench.replay import (
    BenchOptions,
    plot_phases,
    print_summary,
    reference_errors,
    run_bench,
    save_overlay_views,
    summarize,
    write_report,
)

__all__ = ["BenchOptions", "frame_numbers", "frame_row", "image_error", "plot_phases", "print_summary",
           "reference_errors", "run_bench", "save_overlay_views", "summarize", "write_report"]
