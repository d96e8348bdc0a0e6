"""Photo experiments (``pipeline=photos``): structure-from-motion methods on
photo data sets, scored by COLMAP's relative-pose AUC against reference poses.

A table of every data set × method (medians over the seeds of a rendered set),
one figure (the AUC against its threshold for each real folder; AUC@3 against
the number of photos for each rendered shape) and the findings the runs
support: which method wins where, and by how much ours trails or leads the
better COLMAP mapper.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mpe3d.harness.experiment.config import RENDERED
from mpe3d.reports import figures
from mpe3d.reports.claims import FAILS, HOLDS, NOT_ENOUGH, Verdict, criterion

THRESHOLDS = (1, 3, 5, 10)  # degrees: the AUC@k the field reports (COLMAP's benchmark, IMC)
AUC = {t: f"pose_auc{t}" for t in THRESHOLDS}
HEADLINE = AUC[3]
# AUC@3 points within which two methods are said to tie: the bar the issue sets
# for ours against the better COLMAP mapper.
TIE_POINTS = 1.0
OURS = "bundle"
COLMAP_MAPPERS = ("colmap", "colmap_global")
METHODS = {"bundle": "ours (bundle adjustment)", "colmap": "COLMAP incremental",
           "colmap_global": "COLMAP global"}  # in table order; a plug-in follows under its own name
MARKERS = {"ours (bundle adjustment)": "^", "COLMAP incremental": "o", "COLMAP global": "s"}
STYLES = {"ours (bundle adjustment)": dict(linestyle="--", zorder=3)}  # ours dashed, as in the paper's figures
# the table's other columns: their metric, a median over the seeds
COLUMNS = {"centre error (%)": "centre_error", "RMS (px)": "rms_px", "points": "points_placed",
           "solve (s)": "solve_s"}


def is_photos(frame: pd.DataFrame) -> bool:
    """Whether every run of ``frame`` is a photos run."""
    return len(frame) > 0 and "pipeline" in frame and bool((frame["pipeline"] == "photos").all())


def method_label(solver: str) -> str:
    """A method's name in the table, figure and findings; a plug-in keeps its own."""
    return METHODS.get(solver, str(solver))


def _method_rank(solver: str) -> tuple:
    return (list(METHODS).index(solver), "") if solver in METHODS else (len(METHODS), str(solver))


def _dataset(row) -> tuple[tuple, str, bool]:
    """A run's data set: its sort key, its label, and whether it is rendered."""
    if row["photos.set"] != RENDERED:
        return (0, str(row["photos.set"]), 0, 0), str(row["photos.set"]), False
    count, size = int(row["images.count"]), row.get("images.size")
    return (1, str(row["shape"]), count, size), f"{row['shape']}, {count} photos", True


def labelled(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` with a ``dataset`` label, ``rendered``, the ``method`` label and
    ``order`` (data sets: folders by name, then rendered sets by shape and count;
    methods: ours, COLMAP incremental, COLMAP global, then plug-ins by name)."""
    if frame.empty:
        return frame.assign(dataset=[], rendered=[], order=[])
    found = [_dataset(row) for row in frame.to_dict("records")]
    out = frame.assign(dataset=[label for _, label, _ in found], rendered=[r for _, _, r in found],
                       method=frame["photos.solver"].map(method_label),
                       order=[(key, _method_rank(s)) for (key, _, _), s in zip(found, frame["photos.solver"])])
    sizes = out[out["rendered"]].groupby(["shape", "images.count"])["images.size"].nunique() \
        if "images.size" in out else pd.Series(dtype=int)
    if (sizes > 1).any():  # the same shape and count at two sizes: two data sets
        where = out["rendered"]
        out.loc[where, "dataset"] = out.loc[where, "dataset"] + ", " + out.loc[where, "images.size"].astype(str) + " px"
    return out


def _failed(rows: pd.DataFrame) -> int:
    return int((rows["status"] == "FAILED").sum()) if "status" in rows else 0


def _finished(frame: pd.DataFrame) -> pd.DataFrame:
    return frame[frame["status"] == "FINISHED"] if "status" in frame else frame


def _median(rows: pd.DataFrame, column: str) -> float:
    return float(rows[column].median()) if column in rows and rows[column].notna().any() else float("nan")


def _registered(rows: pd.DataFrame) -> str | None:
    """The photos posed of the reference's, as "11/11" (medians over the seeds)."""
    posed, of = _median(rows, "registered"), _median(rows, "photos")
    if np.isnan(posed):
        return None
    return f"{posed:g}/{of:g}" if not np.isnan(of) else f"{posed:g}"


def table(frame: pd.DataFrame) -> pd.DataFrame:
    """A row per data set and method: the medians over its finished runs (the
    seeds of a rendered set), the runs behind them, and the failed ones."""
    frame = labelled(frame)
    rows = []
    for _, group in sorted(frame.groupby(["dataset", "method"]), key=lambda item: item[1]["order"].iloc[0]):
        done = _finished(group)
        row = {"data set": group["dataset"].iloc[0], "method": group["method"].iloc[0]}
        row.update({f"AUC@{t}": _median(done, AUC[t]) for t in THRESHOLDS})
        row["registered"] = _registered(done)
        row.update({label: _median(done, metric) for label, metric in COLUMNS.items()})
        row["points"] = None if np.isnan(row["points"]) else f"{row['points']:.0f}"  # a count, not 1e+03
        row["features (s)"] = _features_s(frame[frame["dataset"] == row["data set"]])
        row["runs"] = len(done)
        row["failed"] = _failed(group)
        rows.append(row)
    return pd.DataFrame(rows)


def _features_s(dataset: pd.DataFrame) -> float:
    """The data set's extraction and matching time, shared by its methods and
    computed once: the median over its runs."""
    done = _finished(dataset)  # a run that read them from the cache carries the seconds they took then
    if done.empty or not {"extract_s", "match_s"} <= set(done):
        return float("nan")
    return float((done["extract_s"] + done["match_s"]).median())


def _spread(ax, x, values: pd.DataFrame, label: str, colour: str) -> None:
    """Medians of ``values`` (a column per x, a row per run) with bars to their
    smallest and largest, in the style of :mod:`mpe3d.reports.figures`."""
    median, low, high = values.median(), values.min(), values.max()
    ax.errorbar(x, median, yerr=[median - low, high - median], label=label, markersize=5, capsize=3,
                linewidth=1.2, alpha=0.9, marker=MARKERS.get(label, "D"), color=colour, **STYLES.get(label, {}))


def _recall_panel(ax, rows: pd.DataFrame, title: str, colours: dict[str, str]) -> None:
    """One real folder: each method's AUC against the threshold."""
    for _, group in sorted(rows.groupby("method"), key=lambda item: item[1]["order"].iloc[0]):
        values = group[[AUC[t] for t in THRESHOLDS]].dropna(how="all")
        if len(values):
            method = group["method"].iloc[0]
            _spread(ax, np.array(THRESHOLDS, float), values, method, colours[method])
    if not ax.lines:  # a folder without reference poses has no AUC to draw
        ax.text(0.5, 0.5, "no reference poses", transform=ax.transAxes, ha="center", color="grey")
    ax.set_xticks(THRESHOLDS, [str(t) for t in THRESHOLDS])
    ax.set_xlabel("threshold (degrees)", fontsize=8)
    ax.set_title(title, fontsize=9)


def _count_panel(ax, rows: pd.DataFrame, title: str, colours: dict[str, str]) -> None:
    """One rendered shape: each method's AUC@3 against the number of photos."""
    counts = sorted(rows["images.count"].unique())
    for _, group in sorted(rows.groupby("method"), key=lambda item: item[1]["order"].iloc[0]):
        values = group.pivot_table(index="seed", columns="images.count", values=HEADLINE, aggfunc="median")
        if values.notna().any().any():
            method = group["method"].iloc[0]
            _spread(ax, values.columns.to_numpy(float), values, method, colours[method])
    ax.set_xticks(counts, [f"{c:g}" for c in counts])
    ax.set_xlabel("photos", fontsize=8)
    ax.set_title(f"{title} (rendered)", fontsize=9)


def figure(frame: pd.DataFrame):
    """The recall summary: a panel per real folder (AUC against the threshold,
    a line per method), then a panel per rendered shape (AUC@3 against the
    number of photos); medians over the seeds, bars from the smallest to the
    largest."""
    import matplotlib.pyplot as plt

    done = labelled(_finished(frame))
    done = done.loc[sorted(done.index, key=done["order"].get)]
    folders, rendered = done[~done["rendered"]], done[done["rendered"]]
    rows = [(part, kind) for part, kind in ((folders, "dataset"), (rendered, "shape")) if len(part)]
    width = max(part[kind].nunique() for part, kind in rows) if rows else 1
    fig, axes = plt.subplots(max(len(rows), 1), width, squeeze=False, sharey=True,
                             figsize=(max(figures.PANEL_WIDTH * width, 6.0), figures.PANEL_HEIGHT * max(len(rows), 1)))
    ranks = {method: order[1] for method, order in zip(done["method"], done["order"])}
    colours = {m: f"C{i}" for i, m in enumerate(sorted(ranks, key=ranks.get))}  # a method's in every panel
    seen: dict[str, object] = {}
    for line, (part, kind) in enumerate(rows):
        names = list(dict.fromkeys(part[kind]))
        for col, ax in enumerate(axes[line]):
            if col >= len(names):
                ax.set_visible(False)
                continue
            panel = _recall_panel if kind == "dataset" else _count_panel
            panel(ax, part[part[kind] == names[col]], str(names[col]), colours)
            ax.set_ylim(0, 100)
            ax.set_ylabel("pose AUC (%)" if kind == "dataset" else "pose AUC@3 (%)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3, linewidth=0.5)
            for handle, label in zip(*ax.get_legend_handles_labels()):
                seen.setdefault(label, handle)
    fig.legend(list(seen.values()), list(seen), loc="upper center", ncol=min(max(len(seen), 1), 4),
               fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout()
    return fig


def _points(value: float) -> str:
    return f"{value:.1f}"


def _seconds(value: float) -> str:
    return f"{value:.3g} s"


def dataset_finding(rows: pd.DataFrame) -> tuple[str, float | None]:
    """One data set's finding (a sentence), and ours minus the better COLMAP
    mapper in AUC@3 points (None: not both ran, or no reference poses)."""
    done = _finished(rows)
    name = rows["dataset"].iloc[0]
    order = {m: o for m, o in zip(rows["method"], rows["order"])}
    auc = done.groupby("method")[HEADLINE].median().dropna() if HEADLINE in done else pd.Series(dtype=float)
    posing = done[done["registered"] >= 2] if "registered" in done else done  # a method that posed nothing is not fast
    solve = posing.groupby("method")["solve_s"].median().dropna() if "solve_s" in done else pd.Series(dtype=float)
    solve = solve[sorted(solve.index, key=order.get)]
    parts, margin = [], None
    failed = [f"{m} {_failed(g)} of {len(g)} runs" for m, g in sorted(rows.groupby("method"), key=lambda i: order[i[0]])
              if _failed(g)]
    if failed:
        parts.append("failed: " + ", ".join(failed))
    if auc.empty:
        posed = [f"{m} {_registered(g)}" for m, g in sorted(done.groupby("method"), key=lambda i: order[i[0]])]
        parts.append("no reference poses (registered: " + ", ".join(posed) + ")")
    else:
        parts.append(_best(auc[sorted(auc.index, key=order.get)]))
        ours = auc.get(method_label(OURS))
        mappers = auc[[m for m in auc.index if m in {method_label(c) for c in COLMAP_MAPPERS}]]
        if ours is not None and len(mappers):
            mapper, best = mappers.idxmax(), float(mappers.max())
            margin = float(ours) - best
            how = "leads" if margin > 0 else "trails" if margin < 0 else "equals"
            by = f", by {_points(abs(margin))} points" if margin else ""
            parts.append(f"ours {how} {mapper}, the better COLMAP mapper{by} "
                         f"({_points(ours)} against {_points(best)})")
    if len(solve):
        fastest = solve.idxmin()
        others = ", ".join(f"{m} {_seconds(v)}" for m, v in solve.items() if m != fastest)
        parts.append(f"fastest of those posing photos: {fastest} ({_seconds(solve.min())} to solve"
                     + (f"; {others}" if others else "") + ")")
    return f"{name}: " + "; ".join(parts) + ".", margin


def _best(auc: pd.Series) -> str:
    """Which method has the best AUC@3, or which tie within :data:`TIE_POINTS`."""
    auc = auc.sort_values(ascending=False, kind="stable")  # equals stay in method order
    tied = auc[auc >= auc.iloc[0] - TIE_POINTS]
    said = ", ".join(f"{m} {_points(v)}" for m, v in tied.items())
    if len(tied) > 1:
        return f"AUC@3 a tie within {TIE_POINTS:g} point: {said}"
    runner = f", next {auc.index[1]} by {_points(auc.iloc[0] - auc.iloc[1])} points" if len(auc) > 1 else ""
    return f"best AUC@3: {said}{runner}"


@criterion(lambda points: f"ours' median AUC@3 >= the better COLMAP mapper's minus {points:g} point "
           "on every data set with reference poses where both ran")
def ours_within(frame: pd.DataFrame, points: float = TIE_POINTS) -> Verdict:
    """Whether ours reaches the better COLMAP mapper's AUC@3 minus ``points``
    on every data set; the numbers say on how many, and by how much it misses."""
    frame = labelled(frame)
    margins = {}
    for name, rows in frame.groupby("dataset", sort=False):
        margin = dataset_finding(rows)[1]
        if _failed(rows[rows["photos.solver"] == OURS]):  # a failed run of ours is a miss, never left out
            margin = -np.inf
        if margin is not None:
            margins[name] = (margin, bool(rows["rendered"].iloc[0]))
    if not margins:
        return Verdict(NOT_ENOUGH, "no data set with reference poses where ours and a COLMAP mapper ran",
                       len(_finished(frame)))
    within = [n for n, (m, _) in margins.items() if m >= -points]
    misses = [f"{n} (ours failed)" if m == -np.inf else f"{n} by {_points(-m)} points"
              for n, (m, _) in margins.items() if m < -points]
    real = [n for n, (_, rendered) in margins.items() if not rendered]
    folders = f" ({sum(n in within for n in real)} of {len(real)} real folders)" if real else ""
    numbers = (f"ours within {points:g} point of the better COLMAP mapper's AUC@3, or ahead, on {len(within)} "
               f"of {len(margins)} data sets{folders}" + (f"; misses: {', '.join(misses)}" if misses else ""))
    return Verdict(HOLDS if not misses else FAILS, numbers, len(_finished(frame)))


def findings(frame: pd.DataFrame) -> list[str]:
    """The findings the runs support, a sentence per data set (in table
    order), then the overall one."""
    frame = labelled(frame)
    ordered = sorted(frame.groupby("dataset", sort=False), key=lambda item: min(item[1]["order"])[0])
    lines = [dataset_finding(rows)[0] for _, rows in ordered if len(_finished(rows))]
    overall = ours_within(frame)
    if overall.verdict != NOT_ENOUGH:
        lines.append(overall.numbers[0].upper() + overall.numbers[1:] + ".")
    return lines


def write_section(frame: pd.DataFrame, report) -> None:
    """The photos table, its figure and the findings, from every run of
    ``frame`` (the failed ones counted in the table)."""
    report.table(table(frame), f"{report.current}_photos",
                 "Structure from motion on photos: a row per data set and method, medians over the "
                 "seeds of a rendered set. AUC@k: COLMAP's relative-pose AUC (per cent) up to k degrees "
                 "over every pair of the reference's photos, a pair a method did not pose scored 180°; "
                 "registered: photos posed of the reference's; centre error: the median camera-centre "
                 "error after a similarity, in per cent of the reference centres' extent; solve: the "
                 "method's own time; features: extraction and matching, computed once per data set "
                 "and shared by its methods; '–': no reference poses, or no finished run.")
    if len(_finished(frame)):
        report.figure(figure(frame), f"{report.current}_photos_auc",
                      "Pose AUC: against its threshold for each real folder, a line per method; "
                      "AUC@3 against the number of photos for each rendered shape; medians over the "
                      "seeds, bars from the smallest to the largest.")
    lines = findings(frame)
    if lines:
        report.heading("Findings: which method wins where", level=3)
        report.text(f"From the runs above (medians over seeds); a tie is within {TIE_POINTS:g} point of AUC@3.")
        for line in lines:
            report.text(line)
