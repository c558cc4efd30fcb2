"""Render passes: G-buffer, ray generation, effect accumulation, shading."""
