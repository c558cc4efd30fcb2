"""Interactive window of `rtwalk view` (moderngl-window + imgui)."""
