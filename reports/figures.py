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
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from mpe3d.reports.claims import ACCEPTABLE_CD  # noqa: E402
from mpe3d.reports.load import CD, METRIC_LABELS  # noqa: E402

MARKERS = {"baseline (MDS)": "s", "baseline (authors': zero-filled average)": "s", "3DMPE (paper)": "o",
           "ours (refine)": "^", "ours (factorize)": "v"}
# Ours is dashed and drawn under the paper's curves: where both are exact they
# coincide, and the paper's must stay visible.
# The authors' baseline is ours drawn hollow and dotted: the same family, another average.
STYLES = {"ours (refine)": dict(linestyle="--", zorder=2), "ours (factorize)": dict(linestyle=":", zorder=2),
          "baseline (authors': zero-filled average)": dict(linestyle=":", markerfacecolor="none")}
PANEL_WIDTH, PANEL_HEIGHT = 3.6, 2.7
LOG_METRICS = {"cd_x100", "emd_x100", "roa", "cd", "emd", "runtime_s"}
# Below this a metric is exact to rounding: drawn on a marked band at the
# bottom instead of stretching the axis over ten more decades.
FLOOR = 1e-6
DECADES = 2.0  # a y axis goes log when its values span at least this many decades


def _panel_title(key: str, value) -> str:
    if key == "projections":
        return f"{value} projections"
    if key == "noise.amplitude":
        return f"p = {value:g}"
    return f"{key} = {value}"


def _style(label: str) -> dict:
    method = label.split(",")[0]
    return {"marker": MARKERS.get(method, "D"), **STYLES.get(method, {})}


def _errorbar(ax, x, mean, std, label):
    """One series with standard-deviation bars; on a log axis, values under
    :data:`FLOOR` sit on the "exact" band and their bars stay inside it."""
    mean, std = np.asarray(mean, float), np.asarray(std, float)
    lower, upper = std.copy(), std.copy()
    if ax.get_yscale() == "log":
        exact = mean < FLOOR
        lower = np.minimum(std, mean * 0.999)
        mean = np.where(exact, FLOOR / np.sqrt(10), mean)
        lower[exact] = upper[exact] = 0.0
        if exact.any():
            ax._mpe_exact = True
    ax.errorbar(x, mean, yerr=[lower, upper], label=label, markersize=5, capsize=3,
                linewidth=1.2, alpha=0.9, **_style(label))


def _finish_y(ax) -> None:
    """Mark the "exact" band when a series fell below the floor."""
    if getattr(ax, "_mpe_exact", False):
        bottom, top = ax.get_ylim()
        ax.axhspan(FLOOR / 10, FLOOR, color="0.88", zorder=0, label=f"exact (< {FLOOR:g})")
        ax.text(0.01, FLOOR / 10 ** 0.75, f"exact (< {FLOOR:g})", transform=ax.get_yaxis_transform(),
                fontsize=6, color="0.35", va="center")
        ax.set_ylim(FLOOR / 10, max(top, FLOOR * 10))


def _ticks_at_data(ax, values) -> None:
    """Ticks where the data are (128, 256, 512), not at 2×10², 3×10²."""
    values = sorted({float(v) for v in values})
    if ax.get_xscale() == "log" or len(values) <= 10:
        ax.set_xticks(values, [f"{v:g}" for v in values])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())


def _plain_log_labels(ax) -> None:
    """1e-06 rather than mathtext's 10^-6: drawing mathtext labels was most of a figure's time."""
    if ax.get_yscale() == "log":
        ax.yaxis.set_major_locator(matplotlib.ticker.LogLocator(numticks=8))
        ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        low, high = ax.get_ylim()
        if high / max(low, 1e-300) > 1e3:  # minor ticks over many decades: clutter, and slow
            ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())


def _dodge(x: np.ndarray, index: int, count: int, log: bool, span: float) -> np.ndarray:
    """Shift series sideways a little so that equal values do not hide each other."""
    shift = (index - (count - 1) / 2) * 0.012
    return x * 10 ** (shift * np.log10(max(span, 10.0))) if log else x + shift * span


def _spans_decades(values) -> bool:
    values = np.asarray(values, float)
    values = values[np.isfinite(values) & (values > 0)]
    return len(values) > 1 and np.log10(max(values.max(), FLOOR) / max(values.min(), FLOOR)) >= DECADES


def _axes_values(frame, x, x_scale):
    values = frame[x].dropna().unique()
    numeric = pd.api.types.is_numeric_dtype(frame[x])
    return numeric, (np.sort(values.astype(float)) * x_scale if numeric else sorted(map(str, values)))


def line_figure(frame: pd.DataFrame, x: str, metrics: list[str], *, panels: str | None = "projections",
                series: str = "method", logx: bool = False, x_scale: float = 1.0,
                xlabel: str | None = None, logy: bool | None = None):
    """Rows of ``metrics`` against ``x``, one column per value of ``panels``
    (one column when ``panels`` is None), one line per value of ``series``.

    ``logy`` None: log for the error metrics (and runtime) when their values
    span :data:`DECADES` decades or more. A categorical ``x`` gets one tick
    per category.
    """
    columns = sorted(frame[panels].unique(), key=str) if panels else [None]
    fig, axes = plt.subplots(len(metrics), len(columns), squeeze=False,
                             figsize=(max(PANEL_WIDTH * len(columns), 6.0), PANEL_HEIGHT * len(metrics)))
    numeric, xs = _axes_values(frame, x, x_scale)
    position = None if numeric else {v: i for i, v in enumerate(xs)}
    span = (xs.max() / max(xs.min(), 1e-300) if logx else xs.max() - xs.min()) if numeric and len(xs) else 1.0
    labels_seen: dict[str, object] = {}
    for row, metric in enumerate(metrics):
        log = logy if logy is not None else (metric in LOG_METRICS and _spans_decades(frame[metric]))
        for col, value in enumerate(columns):
            ax = axes[row][col]
            if log:
                ax.set_yscale("log")
            if logx and numeric:
                ax.set_xscale("log")
            part = frame if panels is None else frame[frame[panels] == value]
            groups = list(part.groupby(series, sort=True, dropna=False))
            for i, (label, group) in enumerate(groups):
                stats = group.groupby(x, dropna=False)[metric].agg(["mean", "std"]).fillna({"std": 0.0})
                where = (stats.index.to_numpy(float) * x_scale if numeric
                         else np.array([position[str(v)] for v in stats.index], float))
                _errorbar(ax, _dodge(where, i, len(groups), logx and numeric, span),
                          stats["mean"].to_numpy(), stats["std"].to_numpy(), str(label))
            if metric == CD:
                ax.axhline(ACCEPTABLE_CD, color="grey", linestyle="--", linewidth=1,
                           label="CD ≈ 0.2 (acceptable below)")
            _finish_y(ax)
            if numeric:
                _ticks_at_data(ax, xs)
            else:
                ax.set_xticks(range(len(xs)), xs, fontsize=7, rotation=30 if len(xs) > 4 else 0)
            if panels is not None:
                ax.set_title(_panel_title(panels, value), fontsize=9)
            ax.set_xlabel(xlabel or x, fontsize=8)
            ax.set_ylabel(METRIC_LABELS.get(metric, metric), fontsize=8)
            ax.tick_params(labelsize=7)
            _plain_log_labels(ax)
            ax.grid(alpha=0.3, linewidth=0.5)
            for handle, label in zip(*ax.get_legend_handles_labels()):
                labels_seen.setdefault(label, handle)
    # One legend for the figure, below the panels, where it covers no data.
    fig.legend(list(labels_seen.values()), list(labels_seen), loc="upper center",
               ncol=min(len(labels_seen), 3), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout()
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
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, 0.0))
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
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    return fig


