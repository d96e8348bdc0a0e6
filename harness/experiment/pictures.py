"""Pictures of point clouds (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

# Three orthogonal panels (matplotlib axes), each named by the axes it shows and the one it looks along.
PANELS = (("front (x, y; looking along z)", 0, 1), ("top (x, z; looking along y)", 0, 2),
         ("side (z, y; looking along x)", 2, 1))
# Edges of the face's colour and no width look like no edges, and they let Agg
# stamp one rasterised marker per point (draw_markers) instead of filling each
# point's path: 3.9 -> 0.4 ms a scatter of 1,024 points.
TRUTH_STYLE = dict(s=14, c="#9ecae1", edgecolors="#9ecae1", linewidths=0, alpha=0.7,
                   label="ground truth")
OURS_STYLE = dict(s=1.5, c="#b2182b", edgecolors="#b2182b", linewidths=0,
                  label="reconstruction (aligned)")


def draw_comparison(truth: np.ndarray, reconstruction: np.ndarray, path: Path | BinaryIO,
                    title: str = "", dpi: int = 110) -> Path | BinaryIO:
    """Ground truth against the aligned reconstruction in three labelled
    orthogonal panels: the truth as wide pale discs, ours as small dark dots
    on top, so that where they coincide both stay visible."""
    from PIL import Image

    figure = _comparison_figure()
    canvas = figure["figure"].canvas
    both = np.vstack([truth, reconstruction])
    lo, hi = both.min(axis=0), both.max(axis=0)
    centre, half = (lo + hi) / 2, max((hi - lo).max() / 2, 1e-12) * 1.05
    for ax, (_, a, b), (pale, dark) in zip(figure["axes"], PANELS, figure["dots"]):
        pale.set_offsets(truth[:, [a, b]])
        dark.set_offsets(reconstruction[:, [a, b]])
        ax.set_xlim(centre[a] - half, centre[a] + half)
        ax.set_ylim(centre[b] - half, centre[b] + half)
    figure["title"].set_text(title)
    canvas.restore_region(_background(figure, dpi))
    for ax, dots in zip(figure["axes"], figure["dots"]):
        for artist in dots:
            ax.draw_artist(artist)
    figure["figure"].draw_artist(figure["title"])
    # opaque, so RGB; zlib level 3 encodes in half the time of the default 6,
    # and the file is no larger
    Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3]).save(path, format="png",
                                                                   compress_level=3)
    return path


FIGURE_CACHE: dict = {}


def _comparison_figure() -> dict:
    """The comparison's figure, made once per process: a sweep draws one
    picture per run, and its frames, labels and legend, which no run changes
    (there are no ticks), cost most of a picture. They are drawn once per dpi
    and kept as a background; each run draws only its points and title."""
    if FIGURE_CACHE:
        return FIGURE_CACHE
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.path import Path

    fig = Figure(figsize=(9.6, 3.6))
    FigureCanvasAgg(fig)  # its own canvas: pyplot never sees, draws on or closes it
    axes = fig.subplots(1, 3)
    none = np.empty((0, 2))
    dots = []
    # 16-gons, not the circle marker: Agg measures each scatter's marker path
    # before stamping it, and the circle's Bezier curves took 1.1 ms of root
    # finding a scatter (6 a picture); 4 pixels wide, a 16-gon is a disc
    disc = Path.unit_regular_polygon(16)
    for ax, (name, a, b) in zip(axes, PANELS):
        dots.append((ax.scatter(none[:, 0], none[:, 1], marker=disc, **TRUTH_STYLE),
                     ax.scatter(none[:, 0], none[:, 1], marker=disc, **OURS_STYLE)))
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("xyz"[a], fontsize=8, labelpad=1)
        ax.set_ylabel("xyz"[b], fontsize=8, labelpad=1)
        ax.set_xticks([])  # unit-diagonal coordinates: the ticks would say nothing
        ax.set_yticks([])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, markerscale=2.5,
               frameon=False)
    fig.subplots_adjust(left=0.03, right=0.99, bottom=0.14, top=0.84, wspace=0.12)
    FIGURE_CACHE.update(figure=fig, axes=axes, dots=dots, title=fig.suptitle("", fontsize=10),
                   backgrounds={})
    return FIGURE_CACHE


def _background(figure: dict, dpi: int):
    """The figure without points or title at ``dpi``, drawn once."""
    fig = figure["figure"]
    fig.set_dpi(dpi)
    if dpi not in figure["backgrounds"]:
        for artist in (*np.ravel(figure["dots"]), figure["title"]):
            artist.set_visible(False)
        fig.canvas.draw()
        figure["backgrounds"][dpi] = fig.canvas.copy_from_bbox(fig.bbox)
        for artist in (*np.ravel(figure["dots"]), figure["title"]):
            artist.set_visible(True)
    return figure["backgrounds"][dpi]


def comparison_png(truth: np.ndarray, reconstruction: np.ndarray, title: str = "") -> bytes:
    """:func:`draw_comparison` as PNG bytes, small enough to keep with every run."""
    import io

    buffer = io.BytesIO()
    draw_comparison(truth, reconstruction, buffer, title, dpi=72)
    return buffer.getvalue()
