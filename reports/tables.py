"""Tables shaped like the paper's: ``DataFrame -> DataFrame`` ready to write."""

from __future__ import annotations

import pandas as pd

from mpe3d.reports.load import CD, EMD, METRIC_LABELS, SETTING_LABELS

PUBLISHED_NOTE = "published, ShapeNet"
# The paper's column order: learning-based methods, then its baseline and 3DMPE.
PUBLISHED_ORDER = ["PSGN", "3D-LMNet", "Baseline[3D-LMNet paper]", "Our BL", "3DMPE(F)", "3DMPE(V)"]


def summary(frame: pd.DataFrame, by: list[str], metrics: list[str]) -> pd.DataFrame:
    """Mean and standard deviation of ``metrics`` per group of ``by``, and the run count."""
    # dropna=False: a solver leaves the other solvers' options empty, and its
    # rows must not vanish with them.
    grouped = frame.groupby(by, sort=True, dropna=False)
    out = grouped[metrics].agg(["mean", "std"])
    out.columns = [f"{METRIC_LABELS.get(m, m).split(' (')[0]} {stat}" for m, stat in out.columns]
    out.insert(0, "runs", grouped.size())
    return out.reset_index()


def category_of(shape: str) -> str:
    """The paper category a bundled shape stands in for (guitar -> rifle)."""
    from mpe3d.harness.scene.shapes import bundled_manifest

    entry = bundled_manifest().get(shape)
    return entry["paper_category"] if entry else shape


def allmetrics(frame: pd.DataFrame, published: pd.DataFrame,
               published_note: str = PUBLISHED_NOTE) -> pd.DataFrame:
    """Paper Table allmetrics: a row per category and metric, the published methods
    first (labelled "published, ShapeNet"), then what our runs measured.

    CD and EMD are on the scale of the authors' code (100 x mean distance).
    """
    measured = frame.assign(category=frame["shape"].map(category_of),
                            column=frame["method"] + " " + frame["projections"].map(SETTING_LABELS))
    baseline = measured["solver.name"] == "baseline"  # blind to the projections: one column
    measured.loc[baseline, "column"] = measured.loc[baseline, "method"]
    long = measured.melt(id_vars=["category", "column"], value_vars=[CD, EMD],
                         var_name="metric", value_name="value")
    long["metric"] = long["metric"].map({CD: "CD", EMD: "EMD"})
    ours = long.pivot_table(index=["category", "metric"], columns="column", values="value",
                            aggfunc="mean")
    covered = sorted(ours.index.get_level_values(0).unique())
    # Both means over the same categories: the published "mean" row averages all
    # of the paper's, so over fewer it is recomputed from the published rows.
    listed = set(published["category"]) - {"mean"}
    mean = "mean" if set(covered) == listed else f"mean of {len(covered)}: {', '.join(covered)}"
    for metric in ("CD", "EMD"):
        ours.loc[(mean, metric), :] = ours.xs(metric, level="metric").mean()
    same = published[published["category"].isin(covered)]
    same = same.groupby(["metric", "method"], as_index=False)["value"].mean().assign(category=mean) \
        if mean != "mean" else published[published["category"] == "mean"]
    published = pd.concat([published[published["category"] != "mean"], same], ignore_index=True)
    paper = published.pivot_table(index=["category", "metric"], columns="method", values="value")
    paper = paper[[m for m in PUBLISHED_ORDER if m in paper] + [m for m in paper if m not in PUBLISHED_ORDER]]
    paper.columns = [f"{m} ({published_note})" for m in paper.columns]
    table = ours.join(paper, how="left")
    order = list(paper.columns) + sorted(ours.columns, key=_column_order)
    categories = [c for c in ours.index.get_level_values(0).unique() if c != mean] + [mean]
    table = table.reindex(pd.MultiIndex.from_product([categories, ["CD", "EMD"]]))[order]
    return table.reset_index(names=["category", "metric"])


def _column_order(column: str) -> tuple:
    rank = {"baseline": 0, "3DMPE": 1, "ours": 2}
    return rank.get(column.split()[0], 3), column


COLMAP_NOTE = "published, ShapeNet chair"
TRACK_METHODS = {"bundle": "ours (bundle adjustment)", "sgd": "3DMPE (paper)", "refine": "ours (refine)"}


def _mean(rows: pd.DataFrame, column: str) -> float:
    return float(rows[column].mean()) if column in rows and rows[column].notna().any() else float("nan")


def colmap(frame: pd.DataFrame, published: pd.DataFrame) -> pd.DataFrame:
    """Paper Table colmap: the published rows, then COLMAP per photo count and
    3DMPE from 4 projections as our runs measured them (CD, EMD x 100)."""
    rows = []
    for method, part in published.groupby("method", sort=False):
        values = dict(zip(part["metric"], part["value"]))
        rows.append({"pipeline": f"{method} ({COLMAP_NOTE})", "input": "photos" if "COLMAP" in method
                     else "projections, known correspondences",
                     "perspectives": 250 if "COLMAP" in method else 4,
                     "EMD": values.get("EMD"), "CD": values.get("CD")})
    photos = frame[frame["pipeline"] == "colmap"]
    for count, part in photos.groupby("images.count"):
        rows.append({"pipeline": "COLMAP", "input": "photos", "perspectives": int(count),
                     "registered": f"{_mean(part, 'registered_images'):.0f}",
                     "points": f"{_mean(part, 'colmap_points'):.0f}",
                     "EMD": _mean(part, EMD), "CD": _mean(part, CD),
                     "time (s)": _mean(part, "runtime_s"), "runs": len(part)})
    points = frame[frame["pipeline"] != "colmap"]
    for (method, setting), part in points.groupby(["method", "projections"]):
        rows.append({"pipeline": f"{method} {SETTING_LABELS.get(setting, setting)}",
                     "input": "projections, known correspondences",
                     "perspectives": int(part["views"].iloc[0]), "points": f"{_mean(part, 'points'):.0f}",
                     "EMD": _mean(part, EMD), "CD": _mean(part, CD),
                     "time (s)": _mean(part, "runtime_s"), "runs": len(part)})
    columns = ["pipeline", "input", "perspectives", "registered", "points", "EMD", "CD", "time (s)", "runs"]
    return pd.DataFrame(rows).reindex(columns=columns)


def colmap_tracks(frame: pd.DataFrame) -> pd.DataFrame:
    """COLMAP's feature tracks fed to mpe3d: track counts per photo count, and
    each method's CD and median distance (x 100) to COLMAP's triangulation of
    the same tracks, its CD to the surface, and how many of its points are
    unplaced (left out of those scores)."""
    rows = []
    for count, part in frame[frame["pipeline"] == "colmap"].groupby("images.count"):
        row = {"photos": int(count), "tracks >= 2 views": _mean(part, "tracks_ge2"),
               "tracks >= 3 views": _mean(part, "tracks_ge3"),
               "triangulated by COLMAP": _mean(part, "tracks_triangulated"),
               "photos tied together": _mean(part, "tracks_photos_tied")}
        for key, label in TRACK_METHODS.items():
            row[f"{label}: CD to COLMAP"] = _mean(part, f"tracks_{key}_cd_x100")
            row[f"{label}: median to COLMAP"] = _mean(part, f"tracks_{key}_median_x100")
            row[f"{label}: CD to surface"] = _mean(part, f"tracks_{key}_surface_cd_x100")
            row[f"{label}: time (s)"] = _mean(part, f"tracks_{key}_s")
            # left out of its scores: seen once, or of weak geometry (bundle adjustment)
            row[f"{label}: unplaced"] = _mean(part, f"tracks_{key}_unplaced")
        rows.append(row)
    return pd.DataFrame(rows)
