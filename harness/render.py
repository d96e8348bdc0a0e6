"""Pictures of point clouds (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np

# Three orthogonal views, each named by the axes it shows and the one it looks along.
VIEWS = (("front (x, y; looking along z)", 0, 1), ("top (x, z; looking along y)", 0, 2),
         ("side (z, y; looking along x)", 2, 1))
TRUTH_STYLE = dict(s=14, c="#9ecae1", edgecolors="none", alpha=0.7, label="ground truth")
OURS_STYLE = dict(s=1.5, c="#b2182b", edgecolors="none", label="reconstruction (aligned)")


def render_comparison(truth: np.ndarray, reconstruction: np.ndarray, path: Path | BinaryIO,
                      title: str = "", dpi: int = 110) -> Path | BinaryIO:
    """Ground truth against the aligned reconstruction in three labelled
    orthogonal views: the truth as wide pale discs, ours as small dark dots
    on top, so that where they coincide both stay visible."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    both = np.vstack([truth, reconstruction])
    lo, hi = both.min(axis=0), both.max(axis=0)
    centre, half = (lo + hi) / 2, max((hi - lo).max() / 2, 1e-12) * 1.05
    fig, axes = plt.subplots(1, 3, figsize=(9.6, 3.6))
    for ax, (name, a, b) in zip(axes, VIEWS):
        ax.scatter(truth[:, a], truth[:, b], **TRUTH_STYLE)
        ax.scatter(reconstruction[:, a], reconstruction[:, b], **OURS_STYLE)
        ax.set_xlim(centre[a] - half, centre[a] + half)
        ax.set_ylim(centre[b] - half, centre[b] + half)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("xyz"[a], fontsize=8, labelpad=1)
        ax.set_ylabel("xyz"[b], fontsize=8, labelpad=1)
        ax.set_xticks([])  # unit-diagonal coordinates: the ticks would say nothing
        ax.set_yticks([])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, markerscale=2.5,
               frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    # Fixed margins: tight_layout would double the cost of a picture per run.
    fig.subplots_adjust(left=0.03, right=0.99, bottom=0.14, top=0.84 if title else 0.92, wspace=0.12)
    fig.savefig(path, dpi=dpi, format="png")
    plt.close(fig)
    return path


def comparison_png(truth: np.ndarray, reconstruction: np.ndarray, title: str = "") -> bytes:
    """:func:`render_comparison` as PNG bytes, small enough to keep with every run."""
    import io

    buffer = io.BytesIO()
    render_comparison(truth, reconstruction, buffer, title, dpi=72)
    return buffer.getvalue()
