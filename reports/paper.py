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

from mpe3d.harness.identity import code_identity

from . import figures, tables
from .claims import claims_table
from .document import Report
from .load import CD, EMD, ROA, finished, published

METRICS = [CD, EMD, ROA]


def _allmetrics(table: str):
    def render(frame: pd.DataFrame, report: Report) -> None:
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
    return render


def _smart_init(frame: pd.DataFrame, report: Report) -> None:
    report.figure(figures.init_bars(frame), "smart_init",
                  "Fig. smart_init_experiment: mean CD from a random (blue) and the smart (orange) "
                  "start, per shape; error bars: standard deviation over repeats.")
    report.table(tables.summary(frame, ["projections", "shape", "init"], [CD, EMD, ROA, "iterations"]),
                 "smart_init", "Table smart_init: 3DMPE from random and smart starts (at most 200 "
                 "iterations), mean and standard deviation over repeats.")


def _noise(kind: str):
    def render(frame: pd.DataFrame, report: Report) -> None:
        name = f"noise_{kind}"
        report.figure(figures.line_figure(frame, "noise.fraction", [CD], panels="noise.amplitude",
                                          x_scale=100, xlabel="corrupted points q (%)"), name,
                      f"Fig. {'gaussian_noise' if kind == 'distance' else 'perm_noise'}: CD against "
                      f"the share q of corrupted points ({kind} noise), one panel per amplitude p; "
                      "mean over shapes and repeats.")
        report.table(tables.summary(frame, ["noise.amplitude", "noise.fraction", "method"], METRICS),
                     name, f"The numbers behind Fig. {name}.")
    return render


def _sweep_of(x: str, name: str, caption: str, logx: bool = False):
    def render(frame: pd.DataFrame, report: Report) -> None:
        report.figure(figures.line_figure(frame, x, ["runtime_s"], logx=logx), f"{name}_runtime",
                      f"Runtime against {caption} (Fig. viewpoints_runtime).")
        report.figure(figures.line_figure(frame, x, METRICS, logx=logx), f"{name}_metrics",
                      f"CD, EMD and ROA against {caption}.")
        report.table(tables.summary(frame, ["projections", x, "method"], [*METRICS, "runtime_s"]),
                     name, f"The numbers behind the {name} figures.")
    return render


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


def _angle_band(frame: pd.DataFrame, report: Report) -> None:
    report.figure(figures.line_figure(frame, "angle_range", [CD, ROA], logx=True,
                                      xlabel="angle band θr (degrees)"), "angle_band",
                  "Fig. angle_noise: CD and ROA against the angle band θr (log axis).")
    report.table(tables.summary(frame, ["projections", "angle_range", "method"], METRICS),
                 "angle_band", "The numbers behind Fig. angle_noise.")


@dataclass(frozen=True)
class Experiment:
    name: str  # the sweep's name, i.e. the MLflow experiment
    title: str
    render: Callable[[pd.DataFrame, Report], None]


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
)
BY_NAME = {e.name: e for e in RECIPE}


def _generic(frame: pd.DataFrame, report: Report, varying: list[str]) -> None:
    by = [k for k in varying if k in frame and k != "seed"] or ["method"]
    report.table(tables.summary(frame, by, [*METRICS, "runtime_s"]), _slug(report, "summary"),
                 "Mean and standard deviation over repeats of every varying setting.")


def _slug(report: Report, stem: str) -> str:
    existing = {p.stem for p in (report.out / "tables").glob("*.md")}
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
    listed = ", ".join(f"{code}{' (this code)' if code == current else ''}: {n} run(s)"
                       for code, n in counts.items())
    if len(counts) == 1:
        return f"Computed by code {listed}.", ""
    return (f"These runs were computed by {len(counts)} different versions of the code ({listed}); "
            "rerun the sweep without --reuse-stale to compute them all with this code.",
            f"Mixes runs of {len(counts)} code versions (see the section text).")


def render_section(report: Report, section: Section) -> None:
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
        experiment.render(rows, report)
    else:
        _generic(rows, report, list(section.varying))
    report.note = ""


def write(out: Path, sections: list[Section], title: str, facts: list[str] | None = None) -> Report:
    """Render ``sections`` and the claims they can test into ``out``."""
    start = time.perf_counter()
    report = Report(Path(out), title)
    for line in facts or []:
        report.text(line)
    frames = {s.name: s.frame for s in sections}
    claims = claims_table(frames)
    checked = claims[claims["experiment"].isin(frames)]
    if len(checked):
        report.heading("Claims")
        report.text("Each claim of the paper, tested on the runs below; 'n/a' where a claim "
                    "does not concern that method.")
        mixed = [s.name for s in sections if code_note(finished(s.frame), s.code)[1]]
        report.note = f"Some runs behind them come from other code versions ({', '.join(mixed)})." \
            if mixed else ""
        report.table(checked, "claims", "The paper's claims and their verdicts.")
        report.note = ""
    for section in sections:
        render_section(report, section)
    report.text(f"Rendered in {time.perf_counter() - start:.1f} s.")
    report.write_index()
    return report
