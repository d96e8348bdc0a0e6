"""Pictures of point clouds (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def render_comparison(truth: np.ndarray, reconstruction: np.ndarray, path: Path,
                      title: str = "") -> Path:
    """Ground truth and aligned reconstruction from three viewpoints, overlaid."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 4.4))
    lo = np.minimum(truth.min(axis=0), reconstruction.min(axis=0))
    hi = np.maximum(truth.max(axis=0), reconstruction.max(axis=0))
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    for i, (elev, azim) in enumerate([(20, -60), (20, 30), (80, -90)]):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        ax.scatter(*truth.T, s=2, c="tab:blue", alpha=0.5, label="ground truth")
        ax.scatter(*reconstruction.T, s=2, c="tab:orange", alpha=0.5, label="reconstruction")
        for axis, c in zip("xyz", centre):
            getattr(ax, f"set_{axis}lim")(c - half, c + half)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        if i == 0:
            ax.legend(loc="upper left", fontsize=8, markerscale=4)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
