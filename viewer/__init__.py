"""rtwalk: a walkthrough viewer mixing rasterization and ray tracing."""

__version__ = "0.1.0"
