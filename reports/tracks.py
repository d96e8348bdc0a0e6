"""Real-tracks experiments (``pipeline=tracks``): a table per data set, and
figures of the error against each perturbation, one line per method."""

from __future__ import annotations

from pathlib import PurePath

import pandas as pd

from mpe3d.reports import figures, tables

# The keys that perturb the observations, in the order their figures come.
PERTURBATIONS = ("tracks.wrong_fraction", "tracks.noise_px", "tracks.drop_fraction", "tracks.views")
# What names the data set or the method already (or is a repeat): never a series of its own.
NAMED = ("tracks.path", "tracks.root", "tracks.truth", "tracks.cameras", "tracks.camera",
         "tracks.objective", "solver.name", "seed")
TABLE_METRICS = ["rms_px_clean", "rms_px", "error_3d_clean_median_pct", "error_3d_median_pct",
                 "centre_error_pct", "dropped", "caught", "unplaced", "converged", "runtime_s"]
FIGURE_METRICS = ["rms_px_clean", "error_3d_clean_median_pct"]


def dataset_of(path: str) -> str:
    """A data set's name from its path: the folder of a generic file
    (``house/keypoints.csv`` is "house"), else the file's stem."""
    path = PurePath(str(path))
    return path.parent.name or path.stem


def _labelled(frame: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """``frame`` with its data set, and a ``series`` label: the method, then ``keys``' values."""
    def label(row) -> str:
        return ", ".join([row["method"], *(f"{k.split('.')[-1]}={row[k]}" for k in keys)])

    out = frame.assign(dataset=frame["tracks.path"].map(dataset_of))
    return out.assign(series=out.apply(label, axis=1) if len(out) else [])


def write_section(frame: pd.DataFrame, report, varying: list[str]) -> None:
    """A table per data set (a row per perturbation and method: mean and
    standard deviation over the seeds' draws), then, for each perturbation
    that varies, its figure: the error on the clean observations (and the 3D
    error where the data set has reference points) against it, a panel per
    data set, a line per method."""
    keys = [k for k in PERTURBATIONS if k in frame and frame[k].nunique(dropna=False) > 1]
    others = [k for k in (varying or []) if k in frame and k not in keys and k not in NAMED
              and frame[k].nunique(dropna=False) > 1]
    frame = _labelled(frame, others)
    for dataset, part in frame.groupby("dataset", sort=True):
        metrics = [m for m in TABLE_METRICS if m in part and part[m].notna().any()]
        report.table(tables.summary(part, [*keys, *others, "method"], metrics),
                     f"{report.current}_{dataset}",
                     f"Data set {dataset}: a row per perturbation and method, mean and standard "
                     "deviation over the seeds' draws. The clean-observation RMS compares each "
                     "observation that no wrong match replaced with its coordinates before noise; "
                     "the 3D errors are after the robust similarity onto the reference points, in "
                     "percent of their bounding-box diagonal ('untouched': points no wrong match "
                     "touched).")
    for x in keys:
        rest = [k for k in keys if k != x] + others
        lines = _labelled(frame.drop(columns=["series", "dataset"]), rest)
        metrics = [m for m in FIGURE_METRICS if m in lines and lines[m].notna().any()]
        fig = figures.line_figure(lines, x, metrics, panels="dataset", series="series")
        for ax in fig.axes:  # a data set without reference points has no 3D error to draw
            if not ax.lines:
                ax.text(0.5, 0.5, "no reference points", transform=ax.transAxes, ha="center",
                        color="grey")
        report.figure(fig, f"{report.current}_vs_{x.split('.')[-1]}",
                      f"Error against {x}, a panel per data set, a line per method"
                      + (f" and {', '.join(rest)}" if rest else "")
                      + "; mean over the seeds' draws, bars: standard deviation.")
