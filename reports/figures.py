"""Figures shaped like the paper's: ``DataFrame -> matplotlib Figure``.

Every point is a mean over the runs behind it (shapes and repeats), with a
standard-deviation error bar. The baseline is drawn with squares, the paper's
3DMPE with circles, our refine with triangles; CD axes carry the paper's
acceptability line at CD ≈ 0.2 (Section "Robustness of the Algorithm").
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # files only: no display, and safe in worker processes
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .load import CD, METRIC_LABELS  # noqa: E402

MARKERS = {"baseline (MDS)": "s", "3DMPE (paper)": "o", "ours (refine)": "^"}
ACCEPTABLE_CD = 0.2
PANEL_WIDTH, PANEL_HEIGHT = 3.6, 2.7
LOG_METRICS = {"cd_x100", "emd_x100", "roa", "cd", "emd"}


def _panel_title(key: str, value) -> str:
    if key == "projections":
        return f"{value} projections"
    if key == "noise.amplitude":
        return f"p = {value:g}"
    return f"{key} = {value}"


def _errorbar(ax, x, mean, std, label):
    lower = np.minimum(std, mean * 0.999) if ax.get_yscale() == "log" else std
    ax.errorbar(x, mean, yerr=[lower, std], label=label, marker=MARKERS.get(label, "D"),
                markersize=5, capsize=3, linewidth=1.2)


def line_figure(frame: pd.DataFrame, x: str, metrics: list[str], *, panels: str = "projections",
                series: str = "method", logx: bool = False, x_scale: float = 1.0,
                xlabel: str | None = None):
    """Rows of ``metrics`` against ``x``, one column per value of ``panels``."""
    columns = sorted(frame[panels].unique(), key=str)
    fig, axes = plt.subplots(len(metrics), len(columns), squeeze=False,
                             figsize=(PANEL_WIDTH * len(columns), PANEL_HEIGHT * len(metrics)))
    for row, metric in enumerate(metrics):
        for col, value in enumerate(columns):
            ax = axes[row][col]
            if metric in LOG_METRICS:
                ax.set_yscale("log")
            if logx:
                ax.set_xscale("log")
            part = frame[frame[panels] == value]
            for label, group in part.groupby(series, sort=True):
                stats = group.groupby(x)[metric].agg(["mean", "std"]).fillna({"std": 0.0})
                _errorbar(ax, stats.index.to_numpy(float) * x_scale, stats["mean"].to_numpy(),
                          stats["std"].to_numpy(), label)
            if metric == CD:
                ax.axhline(ACCEPTABLE_CD, color="grey", linestyle="--", linewidth=1,
                           label="CD ≈ 0.2 (acceptable below)")
            ax.set_title(_panel_title(panels, value), fontsize=9)
            ax.set_xlabel(xlabel or x, fontsize=8)
            ax.set_ylabel(METRIC_LABELS.get(metric, metric), fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3, which="both", linewidth=0.5)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8,
               bbox_to_anchor=(0.5, -0.02), frameon=False)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig


def init_bars(frame: pd.DataFrame, metric: str = CD):
    """Random (blue) against smart (orange) start, per shape, as the paper's figure."""
    columns = sorted(frame["projections"].unique())
    fig, axes = plt.subplots(1, len(columns), squeeze=False,
                             figsize=(PANEL_WIDTH * len(columns), PANEL_HEIGHT))
    for ax, setting in zip(axes[0], columns):
        part = frame[frame["projections"] == setting]
        stats = part.groupby(["shape", "init"])[metric].agg(["mean", "std"]).fillna({"std": 0.0})
        shapes = sorted(part["shape"].unique())
        where = np.arange(len(shapes))
        for offset, (init, colour) in zip((-0.2, 0.2), (("random", "tab:blue"), ("smart", "tab:orange"))):
            rows = [stats.loc[(s, init)] if (s, init) in stats.index else None for s in shapes]
            mean = np.array([r["mean"] if r is not None else np.nan for r in rows])
            std = np.array([r["std"] if r is not None else 0.0 for r in rows])
            ax.bar(where + offset, mean, width=0.4, color=colour, label=f"{init} start",
                   yerr=[np.minimum(std, mean * 0.999), std], capsize=3)
        ax.set_yscale("log")
        ax.set_xticks(where, shapes, fontsize=8)
        ax.set_title(f"{setting} projections", fontsize=9)
        ax.set_ylabel(METRIC_LABELS.get(metric, metric), fontsize=8)
        ax.axhline(ACCEPTABLE_CD, color="grey", linestyle="--", linewidth=1)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def visibility_count_bars(frame: pd.DataFrame, views: int):
    """Points visible in at least m = 1..K views, one bar group per m, a bar per shape."""
    counts = frame.groupby("shape")[[f"seen_ge_{m}" for m in range(1, views + 1)]].first()
    fig, ax = plt.subplots(figsize=(PANEL_WIDTH * 1.6, PANEL_HEIGHT * 1.2))
    width = 0.8 / max(len(counts), 1)
    for i, (shape, row) in enumerate(counts.iterrows()):
        ax.bar(np.arange(1, views + 1) + (i - (len(counts) - 1) / 2) * width, row.to_numpy(),
               width=width, label=shape)
    ax.set_xticks(range(1, views + 1))
    ax.set_xlabel("visible in at least m views", fontsize=8)
    ax.set_ylabel("points", fontsize=8)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    return fig


