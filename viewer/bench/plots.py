"""The one plotting helper of every benchmark report (matplotlib, Agg: no display needed).

Studies describe their charts with these few calls, so fonts, sizes, grids and file handling are
the same in every PNG the benchmarks write.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure(nrows: int = 1, ncols: int = 1, size: tuple[float, float] = (9, 4.5), dpi: int = 110, **kw):
    """(figure, axes); `axes` is one Axes for 1x1, else what plt.subplots gives."""
    return pyplot().subplots(nrows, ncols, figsize=size, dpi=dpi, **kw)


def finish(fig, path: Path, title: str | None = None, fontsize: int = 9) -> None:
    """Title, tight layout, write the PNG, free the figure."""
    if title:
        fig.suptitle(title, fontsize=fontsize)
    fig.tight_layout()
    fig.savefig(path)
    pyplot().close(fig)


def _grouped(ax, labels: Sequence[str], series: dict[str, Sequence[float]], horizontal: bool,
             color: str | None = None) -> np.ndarray:
    """One group of bars per label, one bar per series; returns the label positions."""
    pos = np.arange(len(labels))
    k = len(series)
    width = 0.8 / k if k > 1 else 0.8
    draw = ax.barh if horizontal else ax.bar
    for j, (name, values) in enumerate(series.items()):
        draw(pos + (j - (k - 1) / 2) * width, list(values), width, label=name, **({"color": color} if color else {}))
    return pos


def _annotate(ax, pos: np.ndarray, series: dict[str, Sequence[float]], texts: Sequence[str], of: str | None,
              horizontal: bool) -> None:
    """`texts` next to the bars of series `of` (default: the first)."""
    k = len(series)
    names = list(series)
    j = names.index(of) if of is not None else 0
    off = (j - (k - 1) / 2) * (0.8 / k if k > 1 else 0.8)
    values = list(series[names[j]])
    for i, t in enumerate(texts):
        v = values[i] if np.isfinite(values[i]) else 0
        if horizontal:
            ax.text(v, pos[i] + off, f" {t}", va="center", fontsize=6)
        else:
            ax.annotate(t, (pos[i] + off, v), ha="center", va="bottom", fontsize=8)


def barh(ax, labels: Sequence[str], series: dict[str, Sequence[float]], xlabel: str = "", log: bool = False,
         ref: float | None = None, texts: Sequence[str] | None = None, title: str = "", label_size: int = 7,
         color: str | None = None) -> None:
    """Horizontal bars, one group per label and one bar per series (legend when several);
    `ref` draws a vertical line (e.g. 1.0 for ratios), `texts` annotate the bars of the first series."""
    y = _grouped(ax, labels, series, True, color)
    if texts is not None:
        _annotate(ax, y, series, texts, None, True)
    if labels:
        ax.set_yticks(y, list(labels), fontsize=label_size)
    ax.invert_yaxis()
    if log:
        ax.set_xscale("log")
    if ref is not None:
        ax.axvline(ref, color="k", lw=0.8)
    ax.set_xlabel(xlabel)
    if title:
        ax.set_title(title, fontsize=9)
    if len(series) > 1:
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x")


def bars(ax, labels: Sequence[str], series: dict[str, Sequence[float]], ylabel: str = "", log: bool = False,
         texts: Sequence[str] | None = None, texts_of: str | None = None, title: str = "",
         legend_cols: int = 1) -> None:
    """Vertical bars, one group per label and one bar per series (legend when several);
    `texts` annotate the bars of series `texts_of` (default: the first)."""
    x = _grouped(ax, labels, series, False)
    if texts is not None:
        _annotate(ax, x, series, texts, texts_of, False)
    ax.set_xticks(x, list(labels))
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    if len(series) > 1:
        ax.legend(fontsize=7, ncol=legend_cols)
    ax.grid(alpha=0.3, axis="y")


def stacked(ax, x: Sequence[float], layers: dict[str, Sequence[float]], ylabel: str = "ms", xlabel: str = "",
            title: str = "", area: bool = False, colors: dict[str, str] | None = None) -> None:
    """Layers stacked per x: as steps (`area`, for long frame series) or as bars."""
    x = np.asarray(x)
    if area:
        ax.stackplot(x, np.array([list(v) for v in layers.values()]), labels=list(layers), step="mid")
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
        ax.grid(alpha=0.3)
    else:
        bottom = np.zeros(len(x))
        for name, values in layers.items():
            v = np.asarray(values, dtype=float)
            ax.bar(x, v, bottom=bottom, width=0.85, label=name, **({"color": colors[name]}
                                                                  if colors and name in colors else {}))
            bottom += v
        ax.grid(alpha=0.3, axis="y")
    if title:
        ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)


def points(ax, xs: Sequence[float], ys: Sequence[float], texts: Sequence[str] = (), label: str | None = None,
           line: bool = False, color: str | None = None, xlabel: str = "", ylabel: str = "", title: str = ""):
    """Labelled points (joined by a line with `line`); returns the colour used."""
    style = "o-" if line else "o"
    kw = {"color": color} if color else {}
    artist = ax.plot(list(xs), list(ys), style, ms=5, label=label, **kw)[0]
    for x, y, t in zip(xs, ys, texts, strict=False):
        ax.annotate(t, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=6)
    if xlabel:
        ax.set_xlabel(xlabel)
    if ylabel:
        ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    return artist.get_color()
