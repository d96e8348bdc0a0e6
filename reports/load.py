"""Runs from MLflow as a pandas DataFrame, and the paper's published numbers."""

from __future__ import annotations

from importlib.resources import files

import pandas as pd

from mpe3d.harness.experiment.config import KEYS

# How each solver is named in tables and figures: the paper's method is
# "3DMPE (paper)", our exact solver is "ours (refine)".
METHOD_LABELS = {"baseline": "baseline (MDS)", "sgd": "3DMPE (paper)", "refine": "ours (refine)",
                 "factorize": "ours (factorize)",
                 # the authors' literal baseline (baseline.method=authors), beside ours
                 "baseline:authors": "baseline (authors': zero-filled average)"}
SETTING_LABELS = {"fixed": "F", "variable": "V"}

# The CD and EMD scale of the paper's tables: 100 x mean (unsquared) distance,
# as the authors' public code computes them (../shared/reference/README.md).
CD, EMD, ROA = "cd_x100", "emd_x100", "roa"
METRIC_LABELS = {CD: "CD (×100, mean NN distance)", EMD: "EMD (×100, mean distance)",
                 ROA: "ROA (RMS after rigid alignment)", "runtime_s": "runtime (s)",
                 # real tracks (pipeline=tracks)
                 "rms_px_clean": "reprojection RMS, clean observations (px)",
                 "rms_px_all": "reprojection RMS, all observations (px)",
                 "rms_px": "reprojection RMS, kept observations (px)",
                 "error_3d_clean_median_pct": "3D error, untouched points (median, % of diagonal)",
                 "error_3d_median_pct": "3D error (median, % of diagonal)",
                 "centre_error_pct": "camera-centre error (median, % of diagonal)",
                 "converged": "converged (share)"}


def method_label(solver: str, variant=None) -> str:
    """A solver's name in tables and figures; ``variant`` (its ``method``
    option) names a variant that has a label of its own."""
    if isinstance(variant, str) and f"{solver}:{variant}" in METHOD_LABELS:
        return METHOD_LABELS[f"{solver}:{variant}"]
    return METHOD_LABELS.get(solver, solver)


def runs(tracker, experiment: str, hashes=None) -> pd.DataFrame:
    """The latest run of every config of ``experiment``, with a ``method`` column.

    ``hashes`` (config hashes, e.g. of one sweep at one scale) keeps only those
    configs; a config that was never run is simply absent.
    """
    frame = tracker.runs_frame(experiment)
    if frame.empty:
        return frame
    if hashes is not None:
        frame = frame[frame["config_hash"].isin(set(hashes))]
    frame = frame.copy()
    for key, spec in KEYS.items():  # runs logged before a key existed ran at its default
        if not spec.hashed_at_default:
            column = frame[key] if key in frame else pd.Series(index=frame.index, dtype=object)
            frame[key] = column.where(column.notna(), spec.default)
            if isinstance(spec.default, (int, float)):
                frame[key] = pd.to_numeric(frame[key])
    from mpe3d.harness.experiment.execute import pipeline

    variants = frame["solver.method"] if "solver.method" in frame else [None] * len(frame)
    frame["method"] = [method_label(s, v) for s, v in zip(frame["solver.name"], variants)]
    for name in frame["pipeline"].unique():  # a pipeline may name its runs otherwise (COLMAP, bundle)
        rows = frame["pipeline"] == name
        named = [pipeline(name).method_name(row) for row in frame[rows].to_dict("records")]
        frame.loc[rows, "method"] = [m if m is not None else old for m, old in zip(named, frame.loc[rows, "method"])]
    return frame.reset_index(drop=True)


def finished(frame: pd.DataFrame) -> pd.DataFrame:
    """Only the runs that produced metrics."""
    if frame.empty or "status" not in frame:
        return frame
    return frame[frame["status"] == "FINISHED"]


def published(table: str) -> pd.DataFrame:
    """The paper's published numbers of ``table`` (allmetrics, allmetricspix3d or colmap).

    Columns: table, dataset, category, metric (CD or EMD), method, value. The
    learning-based rows (PSGN, 3D-LMNet) are Mandikal et al. (2018) as the
    paper quotes them; none of them were measured on our meshes.
    """
    path = files(__package__) / "data" / "paper_tables.csv"
    with path.open() as handle:
        data = pd.read_csv(handle)
    return data[data["table"] == table].reset_index(drop=True)


def varying_columns(frame: pd.DataFrame) -> tuple[str, ...]:
    """The config keys whose values differ between the runs of ``frame``; a
    solver option counts only if it differs between runs of one solver."""
    keys = [k for k in frame.columns if k in KEYS or k.startswith("solver.")]

    def varies(key: str) -> bool:
        if key.startswith("solver.") and key != "solver.name":
            return bool((frame.groupby("solver.name")[key].nunique() > 1).any())
        return frame[key].nunique() > 1

    return tuple(k for k in keys if varies(k))
