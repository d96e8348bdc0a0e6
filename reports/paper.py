"""The reproduce-paper recipe: which experiment makes which table and figure.

Each paper sweep (``sweeps/paper/*.yaml``) is one experiment; its renderer
turns the experiment's runs into the paper's tables and figures. An
experiment the recipe does not know gets a generic summary table.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pandas as pd

from mpe3d.harness.tracking.identity import code_identity, is_current
from mpe3d.reports import figures, photos, tables, tracks
from mpe3d.reports.claims import claim_lines, claims_table
from mpe3d.reports.document import Report
from mpe3d.reports.load import CD, EMD, METRIC_LABELS, ROA, finished, published, varying_columns
from mpe3d.reports.viewer import add_viewers

METRICS = [CD, EMD, ROA]


def _allmetrics(table: str):
    def write(frame: pd.DataFrame, report: Report) -> None:
        paper = published(table)
        dataset = paper["dataset"].iloc[0] if len(paper) else "paper"
        for m in sorted(frame["visibility.min_views"].unique()):
            part = frame[frame["visibility.min_views"] == m]
            which = "all sampled points" if m == 0 else f"only the points seen in >= {m} views"
            name = table if m == 0 else f"{table}_seen{m}"
            result = tables.allmetrics(part, paper, published_note=f"published, {dataset}")
            report.table(result, name,
                         f"Table {table} ({which}): CD and EMD on the authors' code's scale "
                         f"(100 × mean distance). Columns marked 'published, {dataset}' are the "
                         "paper's numbers on its own data, not measured here; the rest come from "
                         "our runs on the bundled stand-in meshes. F/V: fixed/variable projections.")
    return write


def _smart_init(frame: pd.DataFrame, report: Report) -> None:
    report.figure(figures.init_bars(frame), "smart_init",
                  "Fig. smart_init_experiment: mean CD from a random (blue) and the smart (orange) "
                  "start, per shape; error bars: standard deviation over repeats.")
    report.table(tables.summary(frame, ["projections", "shape", "init"], [CD, EMD, ROA, "iterations"]),
                 "smart_init", "Table smart_init: 3DMPE from random and smart starts (at most 200 "
                 "iterations), mean and standard deviation over repeats.")


def _noise(kind: str):
    def write(frame: pd.DataFrame, report: Report) -> None:
        name = f"noise_{kind}"
        report.figure(figures.line_figure(frame, "noise.fraction", [CD], panels="noise.amplitude",
                                          x_scale=100, xlabel="corrupted points q (%)"), name,
                      f"Fig. {'gaussian_noise' if kind == 'distance' else 'perm_noise'}: CD against "
                      f"the share q of corrupted points ({kind} noise), one panel per amplitude p; "
                      "mean over shapes and repeats.")
        report.table(tables.summary(frame, ["noise.amplitude", "noise.fraction", "method"], METRICS),
                     name, f"The numbers behind Fig. {name}.")
    return write


def _sweep_of(x: str, name: str, caption: str, logx: bool = False):
    def write(frame: pd.DataFrame, report: Report) -> None:
        report.figure(figures.line_figure(frame, x, ["runtime_s"], logx=logx), f"{name}_runtime",
                      f"Runtime against {caption} (Fig. viewpoints_runtime).")
        report.figure(figures.line_figure(frame, x, METRICS, logx=logx), f"{name}_metrics",
                      f"CD, EMD and ROA against {caption}.")
        report.table(tables.summary(frame, ["projections", x, "method"], [*METRICS, "runtime_s"]),
                     name, f"The numbers behind the {name} figures.")
    return write


def _visibility(frame: pd.DataFrame, report: Report) -> None:
    report.figure(figures.line_figure(frame, "visibility.k", METRICS, xlabel="views each point is in (k)"),
                  "visibility", "Fig. visible_metrics: CD, EMD and ROA when each point is in exactly "
                  "k of 8 views.")
    report.table(tables.summary(frame, ["projections", "visibility.k", "method"], METRICS),
                 "visibility", "The numbers behind Fig. visible_metrics.")


def _raytrace_counts(frame: pd.DataFrame, report: Report) -> None:
    views = int(frame["views"].max())
    report.figure(figures.visibility_count_bars(frame, views), "raytrace_visible",
                  f"Fig. raytrace_visible: points visible in at least m of {views} equidistant "
                  "ray-traced views.")
    report.table(tables.summary(frame, ["shape", "visibility.min_views", "projections", "method"],
                                ["points_kept", *METRICS]), "raytrace_visible",
                 "Reconstruction of the points seen in at least m views (points_kept of them).")


def _occlusion(frame: pd.DataFrame, report: Report) -> None:
    # seen_ge_2 counts the sampled points, before visibility.min_views drops any
    frame = frame.assign(unplaceable=1 - frame["seen_ge_2"] / frame["points"])
    report.table(tables.summary(frame, ["shape", "visibility.min_views", "projections", "method"],
                                ["unplaceable", *METRICS]), "occlusion",
                 "Occlusion by the surface (mesh ray casting, not the paper's protocol): CD, EMD "
                 "and ROA on all points and on those seen in at least 2 views, and the share of "
                 "the points that no method can place (seen in fewer than 2).")


def _angle_band(frame: pd.DataFrame, report: Report) -> None:
    report.figure(figures.line_figure(frame, "angle_range", [CD, ROA], logx=True,
                                      xlabel="angle band θr (degrees)"), "angle_band",
                  "Fig. angle_noise: CD and ROA against the angle band θr (log axis).")
    report.table(tables.summary(frame, ["projections", "angle_range", "method"], METRICS),
                 "angle_band", "The numbers behind Fig. angle_noise.")


def _colmap(frame: pd.DataFrame, report: Report) -> None:
    report.table(tables.colmap(frame, published("colmap")), "colmap",
                 "Table colmap: COLMAP on rendered photos of the chair (its points in the mesh frame "
                 "by the similarity of its camera centres onto the true ones) against 3DMPE from 4 "
                 "projections with known correspondences; CD and EMD on the authors' code's scale "
                 "(100 × mean distance) against 2048 surface samples; 'registered' is the photos in "
                 "COLMAP's largest model. Rows marked 'published' are the paper's numbers on its own "
                 "ShapeNet chair and Blender renders, not measured here.")
    if (frame["pipeline"] == "colmap").any():
        report.table(tables.colmap_tracks(frame), "colmap_tracks",
                     "COLMAP's feature tracks (its verified matches joined into tracks, before "
                     "triangulation) fed to mpe3d, as the paper's pipeline did: each cloud is "
                     "aligned by a similarity to COLMAP's own points of the same tracks (least median "
                     "of squares, then least squares on the inliers), and its CD (×100) is taken to "
                     "those points and to the surface samples; the median distance (×100) to "
                     "COLMAP's point of the same track is what a few tracks far out in depth do not "
                     "move.")


@dataclass(frozen=True)
class Experiment:
    name: str  # the sweep's name, i.e. the MLflow experiment
    title: str
    write: Callable[[pd.DataFrame, Report], None]  # its tables and figures into the report


RECIPE = (
    Experiment("paper-allmetrics", "Table allmetrics (ShapeNet categories)", _allmetrics("allmetrics")),
    Experiment("paper-allmetricspix3d", "Table allmetricspix3d (Pix3D categories)",
               _allmetrics("allmetricspix3d")),
    Experiment("paper-smart-init", "Smart against random initialisation", _smart_init),
    Experiment("paper-noise-distance", "Robustness: distance noise", _noise("distance")),
    Experiment("paper-noise-correspondence", "Robustness: wrong correspondences",
               _noise("correspondence")),
    Experiment("paper-views", "Scalability: number of views",
               _sweep_of("views", "views", "the number of views K")),
    Experiment("paper-points", "Scalability: number of points",
               _sweep_of("points", "points", "the number of points N", logx=True)),
    Experiment("paper-visibility", "Visibility: points in exactly k views", _visibility),
    Experiment("paper-raytrace-counts", "Ray-traced visibility counts", _raytrace_counts),
    Experiment("paper-angle-band", "Angle constraints", _angle_band),
    Experiment("paper-occlusion", "Occlusion by the surface (beyond the paper)", _occlusion),
    Experiment("paper-colmap", "Exploratory integration with COLMAP (Table colmap)", _colmap),
)
BY_NAME = {e.name: e for e in RECIPE}


GENERIC_METRICS = [*METRICS, "runtime_s"]


def _generic(frame: pd.DataFrame, report: Report, varying: list[str]) -> None:
    """Any sweep: a table row per (varying keys, solver), and a figure per
    metric against each varying key, a line per solver (and per setting of the
    other categorical keys; shapes and seeds are averaged as repeats)."""
    keys = [k for k in (varying or varying_columns(frame)) if k in frame and k not in ("seed", "solver.name")]
    # a pipeline scores what it can: COLMAP's points have no correspondences, so no ROA
    metrics = [m for m in GENERIC_METRICS if m in frame]
    report.table(tables.summary(frame, [*keys, "method"], metrics), _slug(report, "summary"),
                 "One row per setting and solver: mean and standard deviation over repeats; "
                 "'–' marks an option the row's solver does not have.")
    for x in _independent([k for k in keys if not k.startswith("solver.")], frame):
        others = [k for k in keys if k not in (x, "shape") and not _numeric(frame, k)]
        lines = _series(frame, others)
        for metric in metrics:
            numeric = _numeric(frame, x)
            values = frame[x].dropna()
            logx = numeric and values.min() > 0 and values.max() / values.min() >= 10
            fig = figures.line_figure(lines, x, [metric], panels=None, series="series", logx=logx)
            label = METRIC_LABELS.get(metric, metric)
            report.figure(fig, _slug(report, f"{metric}_vs_{x}", "figures", ".png"),
                          f"{label} against {x}, one line per solver"
                          + (f" and {', '.join(others)}" if others else "")
                          + "; mean over shapes and repeats, bars: standard deviation.")


def _numeric(frame: pd.DataFrame, key: str) -> bool:
    return pd.api.types.is_numeric_dtype(frame[key])


def _independent(keys: list[str], frame: pd.DataFrame) -> list[str]:
    """Drop a key that moves in lockstep with an earlier one (a zip axis): one figure says it."""
    kept: list[str] = []
    for key in keys:
        if frame[key].nunique() < 2:
            continue
        if not any(frame.groupby(k, dropna=False)[key].nunique().max() <= 1
                   and frame.groupby(key, dropna=False)[k].nunique().max() <= 1 for k in kept):
            kept.append(key)
    return kept


def _series(frame: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """``frame`` with a ``series`` label: the solver, then the other keys' values."""
    def label(row) -> str:
        parts = [f"{k.split('.')[-1]}={row[k]}" for k in keys if pd.notna(row[k])]
        return ", ".join([row["method"], *parts])

    return frame.assign(series=frame.apply(label, axis=1) if len(frame) else [])


def _slug(report: Report, stem: str, folder: str = "tables", suffix: str = ".md") -> str:
    stem = "".join(c if c.isalnum() or c in "_-" else "_" for c in stem)
    existing = {p.stem for p in (report.out / folder).glob(f"*{suffix}")}
    name, i = stem, 2
    while name in existing:
        name, i = f"{stem}_{i}", i + 1
    return name


@dataclass
class Section:
    """One experiment's runs and where they came from."""

    name: str
    frame: pd.DataFrame  # latest run per config (FAILED ones included)
    description: str = ""
    source: str = ""  # the sweep file and scale
    planned: int | None = None  # configs in the sweep; None when reporting a whole experiment
    varying: tuple[str, ...] = ()
    code: str = field(default_factory=code_identity)  # the running code, to tell its runs apart
    client: object | None = None  # an MlflowClient to fetch a few runs' clouds for turnable views
    full_runs_per_group: int | None = None  # at the full scale, to mark smaller verdicts provisional


def _counts(section: Section) -> str:
    frame = section.frame
    done = int((frame["status"] == "FINISHED").sum()) if len(frame) else 0
    failed = int((frame["status"] == "FAILED").sum()) if len(frame) else 0
    text = f"{done} finished, {failed} failed"
    if section.planned is not None:
        text += f", {section.planned - len(frame)} not run, of {section.planned} runs"
    return text


def code_note(frame: pd.DataFrame, current: str) -> tuple[str, str]:
    """What code computed these runs (a sentence), and a caption note when it
    was more than one version: numbers of different code are not one experiment."""
    if frame.empty or "code" not in frame:
        return "", ""
    counts = frame["code"].value_counts()
    listed = ", ".join(f"{code}{' (this code)' if is_current(code, current) else ''}: {n} run(s)"
                       for code, n in counts.items())
    ours = {code.split("+")[0] for code in counts.index}  # a plug-in's part is its own, not a version
    if len(ours) == 1:
        return f"Computed by code {listed}.", ""
    return (f"These runs were computed by {len(ours)} different versions of the code ({listed}); "
            "rerun the sweep without --reuse-stale to compute them all with this code.",
            f"Mixes runs of {len(ours)} code versions (see the section text).")


def write_section(report: Report, section: Section) -> None:
    report.current = section.name
    experiment = BY_NAME.get(section.name)
    report.heading(experiment.title if experiment else section.name)
    if section.description:
        report.text(section.description)
    report.text(f"Experiment {section.name}" + (f", sweep {section.source}" if section.source else "")
                + f": {_counts(section)}.")
    rows = finished(section.frame)
    sentence, report.note = code_note(rows, section.code)
    if sentence:
        report.text(sentence)
    errors = section.frame["error"].dropna() if "error" in section.frame else pd.Series(dtype=str)
    errors = errors[errors.astype(str).str.len() > 0]
    for message, n in errors.astype(str).value_counts().head(3).items():
        report.text(f"{n} failed run(s): {message}")
    if rows.empty:
        report.text("No finished runs yet: nothing to show.")
    elif experiment:
        experiment.write(rows, report)
    elif "pipeline" in rows and (rows["pipeline"] == "tracks").all():
        tracks.write_section(rows, report, list(section.varying))
    elif photos.is_photos(rows):  # its failed runs too: the table counts them
        photos.write_section(section.frame[section.frame["pipeline"] == "photos"], report)
    else:
        _generic(rows, report, list(section.varying))
    report.note = ""
    if not rows.empty and section.client is not None:
        add_viewers(report, rows, section.client, section.name)


def added_solvers(frames) -> tuple[str, ...]:
    """The solvers in these runs that are not mpe3d's own (plug-ins), by name."""
    from mpe3d.solvers import SOLVERS

    ours = {name for name, spec in SOLVERS.items() if spec.origin is None}
    names = {name for frame in frames if "solver.name" in frame and "pipeline" in frame
             for name in frame.loc[frame["pipeline"] != "colmap", "solver.name"].dropna()}
    return tuple(sorted(names - ours))


def write(out: Path, sections: list[Section], title: str, facts: list[str] | None = None,
          claims: bool = True, pdf: bool = True) -> Report:
    """Render ``sections`` and (with ``claims``) the claims they can test into
    ``out``; ``pdf`` adds a PDF of every figure."""
    start = time.perf_counter()
    report = Report(Path(out), title, pdf=pdf)
    for line in facts or []:
        report.text(line)
    frames = {s.name: s.frame for s in sections}
    full = {s.name: s.full_runs_per_group for s in sections if s.full_runs_per_group}
    table = claims_table(frames, full_sizes=full, added=added_solvers(frames.values())) if claims \
        else pd.DataFrame(columns=["experiment"])
    checked = table[table["experiment"].isin(frames)]
    if len(checked):
        report.heading("Claims")
        report.text("Each claim of the paper, tested on the runs below; 'n/a' where a claim "
                    "does not concern that method.")
        mixed = [s.name for s in sections if code_note(finished(s.frame), s.code)[1]]
        report.note = f"Some runs behind them come from other code versions ({', '.join(mixed)})." \
            if mixed else ""
        report.folded_table(checked, "claims", "The paper's claims and their verdicts.",
                            *claim_lines(checked))
        report.note = ""
    for section in sections:
        write_section(report, section)
    report.text(f"Rendered in {time.perf_counter() - start:.1f} s.")
    report.write_index()
    return report
