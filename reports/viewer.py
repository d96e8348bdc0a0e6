"""Clouds that can be turned with the mouse: a few tracked runs per experiment,
ground truth against reconstruction, drawn offline by ``assets/viewer.js``.

The clouds come from the runs' own artifacts (``ground_truth.ply`` and the
aligned ``reconstruction.ply``), never recomputed; a run logged without
artifacts is simply not shown.
"""

from __future__ import annotations

import tempfile
from importlib.resources import files
from pathlib import Path

import numpy as np
import pandas as pd

MAX_POINTS = 1200  # per cloud: enough to see the shape, small enough for the page
PER_EXPERIMENT = 3


# What a viewer's caption says of its run, where the run has it.
CAPTION_SCORES = (("roa", "ROA"), ("cd_x100", "CD×100"), ("error_3d_median_pct", "3D error (median, %)"))


def viewer_script() -> str:
    """The viewer's JavaScript, as shipped with the package."""
    return (files(__package__) / "assets" / "viewer.js").read_text()


def pick_runs(frame: pd.DataFrame, count: int = PER_EXPERIMENT) -> pd.DataFrame:
    """Up to ``count`` finished runs of one setting, one per solver, so the
    methods can be compared on the same scene."""
    rows = frame[frame["status"] == "FINISHED"] if "status" in frame else frame
    if rows.empty or "run_id" not in rows:
        return rows.iloc[0:0]
    setting = [c for c in ("shape", "points", "views", "projections", "noise.fraction") if c in rows]
    first = rows.sort_values([*setting, "method"]).iloc[0]
    same = rows
    for key in setting:
        same = same[same[key] == first[key]]
    return same.drop_duplicates("method").sort_values("method").head(count)


def load_clouds(client, run_id: str, limit: int = MAX_POINTS) -> dict | None:
    """``{"truth": [[x, y, z], ...], "ours": [...]}`` from a run's artifacts, or None."""
    import trimesh

    clouds = {}
    with tempfile.TemporaryDirectory(prefix="mpe3d-viewer-") as folder:
        for key, name in (("truth", "ground_truth.ply"), ("ours", "reconstruction.ply")):
            try:
                path = client.download_artifacts(run_id, name, folder)
            except Exception:  # noqa: BLE001 - no artifacts (--no-artifacts): nothing to show
                return None
            clouds[key] = np.asarray(trimesh.load(path).vertices, dtype=float)
    out = {}
    for key, cloud in clouds.items():
        # the same subsample on every render, and the same rows of both clouds when they
        # correspond (COLMAP's points do not: each cloud is sampled on its own)
        rng = np.random.default_rng(0)
        n = len(cloud)
        keep = np.sort(rng.choice(n, limit, replace=False)) if n > limit else np.arange(n)
        out[key] = np.round(cloud[keep], 4).tolist()
    return out


def add_viewers(report, frame: pd.DataFrame, client, experiment: str) -> int:
    """Put up to :data:`PER_EXPERIMENT` turnable clouds of ``frame``'s runs in
    the report; returns how many."""
    shown = 0
    for _, row in pick_runs(frame).iterrows():
        clouds = load_clouds(client, row["run_id"])
        if clouds is None:
            continue
        keys = ("tracks.path", "tracks.wrong_fraction", "tracks.noise_px") \
            if row.get("pipeline") == "tracks" else ("shape", "points", "views", "projections")
        setting = ", ".join(f"{k}={row[k]}" for k in keys if k in row and pd.notna(row[k]))
        scores = ", ".join(f"{label} {row[k]:.3g}" for k, label in CAPTION_SCORES
                           if k in row and pd.notna(row[k]))
        caption = (f"{row['method']}: {setting}; {scores} (run {row['run_id'][:8]}). "
                   "Drag to turn, wheel to zoom.")
        report.viewer(clouds, f"{experiment}-{shown}", caption)
        shown += 1
    return shown


def write_script(out: Path) -> Path:
    path = Path(out) / "viewer.js"
    path.write_text(viewer_script())
    return path
