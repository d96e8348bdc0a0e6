"""The paper's claims as data, each checked against tracked runs.

A :class:`Claim` names the paper's words, where they stand, the experiment
(sweep) whose runs test it and the test itself: a check function with its
thresholds bound as plain parameters. Checking a claim on a DataFrame of runs
gives a :class:`Verdict` (holds / does not hold / not enough runs) with the
numbers behind it, once for the paper's 3DMPE (``sgd``) and once for our
``refine`` where the claim applies to it.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from functools import partial
from typing import Callable

import numpy as np
import pandas as pd

from mpe3d.reports.load import CD

HOLDS, FAILS, NOT_ENOUGH, NOT_APPLICABLE = "holds", "does not hold", "not enough runs", "n/a"
ACCEPTABLE_CD = 0.2  # the paper's acceptability line (Section "Robustness of the Algorithm")


@dataclass(frozen=True)
class Verdict:
    verdict: str
    numbers: str = ""
    runs: int = 0


@dataclass(frozen=True)
class Claim:
    id: str
    statement: str  # the paper's claim, in its words or close to them
    source: str  # where the paper makes it
    experiment: str  # the MLflow experiment (sweep name) whose runs test it
    check: partial  # a criterion below with its thresholds bound
    # the methods it is tested on; the default marks a claim about the method
    # itself, which is also tested on every added method (a plug-in's)
    solvers: tuple[str, ...] = field(default=("sgd", "refine"))

    @property
    def test(self) -> str:
        """The criterion in words, written from the thresholds it is bound to."""
        func = self.check.func
        params = {name: p.default for name, p in inspect.signature(func).parameters.items()
                  if p.default is not inspect.Parameter.empty}
        return func.describe(**{**params, **self.check.keywords})


def criterion(describe: Callable[..., str]):
    """Attach ``describe(**thresholds) -> str`` to a check function."""
    def decorator(func):
        func.describe = describe
        return func
    return decorator


def _finished(frame: pd.DataFrame, solver: str | None) -> pd.DataFrame:
    if frame.empty or "status" not in frame:
        return frame.iloc[0:0]
    rows = frame[frame["status"] == "FINISHED"]
    return rows[rows["solver.name"] == solver] if solver else rows


def _fmt(value: float) -> str:
    return f"{value:.3g}"


@criterion(lambda factor: f"geometric mean of random/smart mean CD over shapes and settings >= {factor:g}")
def smart_beats_random(frame: pd.DataFrame, solver: str, factor: float) -> Verdict:
    """Mean CD from the random start over mean CD from the smart start, per shape
    and setting; holds when their geometric mean is at least ``factor``."""
    rows = _finished(frame, solver)
    if rows.empty or not {"random", "smart"} <= set(rows["init"]):
        return Verdict(NOT_ENOUGH, "needs runs from both starts", len(rows))
    means = rows.groupby(["shape", "projections", "init"])[CD].mean().unstack("init").dropna()
    if means.empty:
        return Verdict(NOT_ENOUGH, "no shape has runs from both starts", len(rows))
    ratio = means["random"] / np.maximum(means["smart"], 1e-300)
    gmean = float(np.exp(np.mean(np.log(ratio))))
    numbers = (f"random/smart CD: geometric mean {_fmt(gmean)}× over {len(ratio)} shape×setting "
               f"groups (min {_fmt(ratio.min())}×, max {_fmt(ratio.max())}×)")
    return Verdict(HOLDS if gmean >= factor else FAILS, numbers, len(rows))


def _selection(column: str, at_least: float | None, among: tuple | None) -> str:
    if among is not None:
        return f"{column} in {{{', '.join(f'{v:g}' for v in among)}}}"
    return f"every {column} >= {at_least:g}" if at_least is not None else f"every value of {column}"


@criterion(lambda column, at_least, among, min_levels, threshold:
           f"median CD <= {threshold:g} for {_selection(column, at_least, among)}, both settings"
           + (f" (needs >= {min_levels} values of {column})" if min_levels > 1 else ""))
def good_where(frame: pd.DataFrame, solver: str, column: str, at_least: float | None = None,
               among: tuple | None = None, min_levels: int = 1,
               threshold: float = ACCEPTABLE_CD) -> Verdict:
    """The median CD of every (``column`` value, setting) group with the value
    ``>= at_least`` (or ``among`` the listed ones) is below ``threshold``;
    needs ``min_levels`` values of ``column``."""
    rows = _finished(frame, solver)
    if rows.empty:
        return Verdict(NOT_ENOUGH, "no finished runs", 0)
    if at_least is not None:
        rows = rows[rows[column] >= at_least]
    if among is not None:
        rows = rows[rows[column].isin(among)]
    levels = sorted(rows[column].unique())
    if len(levels) < min_levels or not levels:
        return Verdict(NOT_ENOUGH, f"needs {max(min_levels, 1)} values of {column}, has {len(levels)}",
                       len(rows))
    medians = rows.groupby([column, "projections"])[CD].median()
    worst = medians.idxmax()
    numbers = (f"median CD per {column} and setting: worst {_fmt(medians.max())} at {column}="
               f"{worst[0]:g} ({worst[1]}), over {len(medians)} groups; line at {threshold:g}")
    return Verdict(HOLDS if medians.max() <= threshold else FAILS, numbers, len(rows))


def _one_alignment(rows: pd.DataFrame, align: str) -> pd.DataFrame:
    """The runs scored under ``align`` (all of them when the runs do not say)."""
    return rows[rows["align"] == align] if "align" in rows else rows


def _noise_medians(frame: pd.DataFrame, solver: str, align: str, min_fraction: float,
                   baseline: str):
    """Median CD per (p, q) for the baseline (its ``method`` ``baseline``) and
    ``solver``, or why there is none."""
    rows = _one_alignment(_finished(frame, None), align)
    if not rows.empty:
        variant = rows["solver.method"] if "solver.method" in rows else pd.Series("smacof", rows.index)
        rows = rows[(rows["solver.name"] == solver)
                    | ((rows["solver.name"] == "baseline") & (variant.fillna("smacof") == baseline))]
    if rows.empty:
        return None, Verdict(NOT_ENOUGH, f"no finished runs scored with align={align}", 0)
    q_max = rows["noise.fraction"].max()
    if q_max < min_fraction or 0.0 not in set(rows["noise.fraction"]):
        return None, Verdict(NOT_ENOUGH, f"needs q = 0 and a q >= {min_fraction}", len(rows))
    medians = rows.groupby(["noise.amplitude", "noise.fraction", "solver.name"])[CD].median().unstack()
    if not {"baseline", solver} <= set(medians.columns) or medians[["baseline", solver]].isna().any().any():
        return None, Verdict(NOT_ENOUGH, f"needs {solver} and the baseline at every (p, q)", len(rows))
    return (medians[["baseline", solver]], rows), None


@criterion(lambda factor, min_fraction, align, baseline: f"for every p, from q=0 to the largest q "
           f"(>= {min_fraction:g}), the baseline's ({baseline}) median CD rises >= {factor:g}× the "
           f"method's, both in CD (absolute) and as a ratio to its own q=0 CD (relative); one "
           f"alignment ({align})")
def degrades_less(frame: pd.DataFrame, solver: str, factor: float, min_fraction: float = 0.5,
                  align: str = "rigid", baseline: str = "authors") -> Verdict:
    """Per noise amplitude p: the baseline's rise in median CD from q = 0 to the
    largest q is at least ``factor`` times the solver's, both absolute (CD at
    the largest q minus CD at q = 0) and relative (their ratio), all runs
    scored with the same alignment. ``baseline`` picks the baseline's
    variant: the paper's claims are about the authors' one."""
    found, verdict = _noise_medians(frame, solver, align, min_fraction, baseline)
    if verdict:
        return verdict
    medians, rows = found
    q_max = rows["noise.fraction"].max()
    parts, ok = [], True
    for p in sorted(rows["noise.amplitude"].unique()):
        start, end = medians.loc[(p, 0.0)], medians.loc[(p, q_max)]
        absolute = end - start
        relative = end / np.maximum(start, 1e-12)
        by_abs = absolute["baseline"] / max(absolute[solver], 1e-12)
        by_rel = (relative["baseline"] - 1) / max(relative[solver] - 1, 1e-12)
        ok &= by_abs >= factor and by_rel >= factor
        parts.append(f"p={p:g}: rise baseline {_fmt(absolute['baseline'])} ({_fmt(relative['baseline'])}×"
                     f" its q=0 CD), {solver} {_fmt(absolute[solver])} ({_fmt(relative[solver])}×)")
    return Verdict(HOLDS if ok else FAILS, f"median CD, q 0→{q_max:g}, align={align}: "
                   + "; ".join(parts), len(rows))


@criterion(lambda min_fraction, align, baseline: f"the baseline's ({baseline}) median CD is above "
           f"the method's at every (p, q) from q=0 to the largest q (>= {min_fraction:g}); one "
           f"alignment ({align})")
def stays_above(frame: pd.DataFrame, solver: str, min_fraction: float = 0.5,
                align: str = "rigid", baseline: str = "authors") -> Verdict:
    """At every noise level (p, q), the baseline's median CD exceeds the solver's."""
    found, verdict = _noise_medians(frame, solver, align, min_fraction, baseline)
    if verdict:
        return verdict
    medians, rows = found
    margin = medians["baseline"] / np.maximum(medians[solver], 1e-300)
    worst = margin.idxmin()
    numbers = (f"baseline/{solver} median CD over {len(margin)} (p, q) levels: lowest "
               f"{_fmt(margin.min())}× at p={worst[0]:g}, q={worst[1]:g}; align={align}")
    return Verdict(HOLDS if margin.min() > 1.0 else FAILS, numbers, len(rows))


_MEASURES = {"run": "runtime", "iteration": "time per iteration"}


def _runtime_medians(frame: pd.DataFrame, solver: str, setting: str, measure: str):
    """Per K: the median of the measure (runtime, or runtime / iterations) and of the iterations."""
    rows = _finished(frame, solver)
    rows = rows[rows["projections"] == setting] if not rows.empty else rows
    if rows.empty:
        return rows, pd.Series(dtype=float), pd.Series(dtype=float)
    iterations = rows["iterations"] if "iterations" in rows else pd.Series(np.nan, index=rows.index)
    value = rows["runtime_s"] / iterations.clip(lower=1) if measure == "iteration" else rows["runtime_s"]
    by_k = pd.DataFrame({"views": rows["views"], "value": value, "iterations": iterations})
    medians = by_k.groupby("views").median()
    return rows, medians["value"], medians["iterations"]


def _iterations_said(iterations: pd.Series) -> str:
    if iterations.isna().all():
        return "iterations not recorded"
    return (f"median iterations {_fmt(iterations.iloc[0])} at K={iterations.index[0]:g} to "
            f"{_fmt(iterations.iloc[-1])} at K={iterations.index[-1]:g}")


@criterion(lambda setting, min_r2, min_levels, measure: f"median {_MEASURES[measure]} against K "
           f"({setting}): line with positive slope and R² >= {min_r2:g}, >= {min_levels} values of "
           "K; the iteration counts beside it")
def linear_runtime(frame: pd.DataFrame, solver: str, setting: str = "variable",
                   min_r2: float = 0.9, min_levels: int = 4, measure: str = "run") -> Verdict:
    """The median ``measure`` (a run's runtime, or its runtime per iteration)
    against K is fitted by a line with positive slope and R² >= ``min_r2``.
    The numbers give the median iteration counts too: early stopping sets
    them, and they scale a run's runtime apart from the cost of an iteration."""
    rows, medians, iterations = _runtime_medians(frame, solver, setting, measure)
    if len(medians) < min_levels:
        return Verdict(NOT_ENOUGH, f"needs {min_levels} values of K, has {len(medians)}", len(rows))
    k, t = medians.index.to_numpy(float), medians.to_numpy()
    slope, intercept = np.polyfit(k, t, 1)
    residual = t - (slope * k + intercept)
    r2 = 1.0 - residual @ residual / max(((t - t.mean()) ** 2).sum(), 1e-300)
    numbers = (f"{setting}: median {_MEASURES[measure]} {_fmt(t[0])} s at K={k[0]:g} to {_fmt(t[-1])} s "
               f"at K={k[-1]:g}; line slope {_fmt(slope)} s per view, R² {r2:.2f}; "
               + _iterations_said(iterations))
    return Verdict(HOLDS if slope > 0 and r2 >= min_r2 else FAILS, numbers, len(rows))


@criterion(lambda setting, max_ratio, min_levels, measure: f"largest median {_MEASURES[measure]} "
           f"over K ({setting}) <= {max_ratio:g}× the smallest, >= {min_levels} values of K; the "
           "iteration counts beside it")
def flat_runtime(frame: pd.DataFrame, solver: str, setting: str = "fixed", max_ratio: float = 2.0,
                 min_levels: int = 3, measure: str = "run") -> Verdict:
    """The largest median ``measure`` over K is at most ``max_ratio`` times the smallest."""
    rows, medians, iterations = _runtime_medians(frame, solver, setting, measure)
    if len(medians) < min_levels:
        return Verdict(NOT_ENOUGH, f"needs {min_levels} values of K, has {len(medians)}", len(rows))
    ratio = medians.max() / max(medians.min(), 1e-12)
    numbers = (f"{setting}: median {_MEASURES[measure]} from {_fmt(medians.min())} s to "
               f"{_fmt(medians.max())} s over K={medians.index.min():g}..{medians.index.max():g} "
               f"({_fmt(ratio)}×); " + _iterations_said(iterations))
    return Verdict(HOLDS if ratio <= max_ratio else FAILS, numbers, len(rows))


@criterion(lambda m, min_share: f"in every shape >= {100 * min_share:g}% of the sampled points are "
           f"visible in >= {m} of the views")
def most_in_three_views(frame: pd.DataFrame, solver: str | None, m: int = 3,
                        min_share: float = 0.5) -> Verdict:
    """In every shape, at least ``min_share`` of the sampled points are visible in >= m views."""
    rows = _finished(frame, None)
    column = f"seen_ge_{m}"
    if rows.empty or column not in rows:
        return Verdict(NOT_ENOUGH, "no finished runs", 0)
    share = rows.groupby("shape").apply(lambda g: (g[column] / g["points"]).mean(), include_groups=False)
    numbers = ", ".join(f"{shape} {100 * v:.0f}%" for shape, v in share.items())
    return Verdict(HOLDS if share.min() >= min_share else FAILS,
                   f"share of points in >= {m} views: {numbers}", len(rows))


@criterion(lambda than, min_speedup: f"per N and setting: {than}'s median runtime >= {min_speedup:g}× "
           f"the method's, and the method's median CD <= {than}'s")
def faster_and_as_exact(frame: pd.DataFrame, solver: str, than: str = "sgd",
                        min_speedup: float = 5.0) -> Verdict:
    """Per N and setting: ``solver`` is ``min_speedup``× faster (median runtime)
    and its median CD is no worse than ``than``'s."""
    rows = _finished(frame, None)
    if rows.empty or not {solver, than} <= set(rows["solver.name"]):
        return Verdict(NOT_ENOUGH, f"needs runs of {solver} and {than}", len(rows))
    medians = rows.groupby(["points", "projections", "solver.name"])[["runtime_s", CD]].median()
    table = medians.unstack("solver.name").dropna()
    speedup = table[("runtime_s", than)] / table[("runtime_s", solver)].clip(lower=1e-9)
    better = (table[(CD, solver)] <= table[(CD, than)] * (1 + 1e-9)).mean()
    numbers = (f"{than}/{solver} runtime: {_fmt(speedup.min())}× to {_fmt(speedup.max())}× over "
               f"{len(table)} groups; {solver}'s median CD no worse in {100 * better:.0f}% of them")
    ok = speedup.min() >= min_speedup and better == 1.0
    return Verdict(HOLDS if ok else FAILS, numbers, len(rows[rows["solver.name"].isin([solver, than])]))


@criterion(lambda below, min_share, often: f"COLMAP's largest model registers < "
           f"{100 * min_share:g}% of the photos in >= {100 * often:g}% of the runs with < {below} photos")
def colmap_fails_below(frame: pd.DataFrame, solver: str | None, below: int = 200,
                       min_share: float = 0.5, often: float = 0.5) -> Verdict:
    """COLMAP "often failed to initialize" with fewer than ``below`` photos."""
    rows = _finished(frame, None)
    if not {"pipeline", "images.count", "registered_share"} <= set(rows.columns):
        return Verdict(NOT_ENOUGH, "no COLMAP runs", 0)
    rows = rows[rows["pipeline"] == "colmap"]
    few = rows[rows["images.count"] < below]
    if few.empty:
        return Verdict(NOT_ENOUGH, f"no COLMAP runs with fewer than {below} photos", 0)
    failed = few["registered_share"] < min_share
    numbers = "; ".join(f"{int(n)} photos: {100 * share:.0f}% registered"
                        for n, share in rows.groupby("images.count")["registered_share"].mean().items())
    return Verdict(HOLDS if failed.mean() >= often else FAILS, numbers, len(rows))


CLAIMS: tuple[Claim, ...] = (
    Claim("smart-init", "Smart initialization outperforms random initialization by an order of "
          "magnitude (CD).", "Sec. 'The Effect of Smart Initialization', Fig. smart_init_experiment",
          "paper-smart-init", partial(smart_beats_random, factor=5.0), solvers=("sgd",)),
    Claim("three-views", "3DMPE reconstructs the point cloud properly if each point is visible from "
          "at least 3 projections.", "Sec. 'Scalability', Fig. visible_metrics", "paper-visibility",
          partial(good_where, column="visibility.k", at_least=3)),
    Claim("angle-90", "For θr >= 90°, 3DMPE can reconstruct the whole object.",
          "Sec. 'Analysis of Angle Constraints', Fig. angle_noise", "paper-angle-band",
          partial(good_where, column="angle_range", at_least=90)),
    Claim("four-five-views", "Typically 4 or 5 projections suffice for high-quality reconstruction.",
          "Sec. 'Scalability', Fig. viewpoints_metrics", "paper-views",
          partial(good_where, column="views", among=(4, 5))),
    Claim("points-independent", "No significant effect of the number of points on accuracy.",
          "Sec. 'Scalability', Fig. points_metrics", "paper-points",
          partial(good_where, column="points", min_levels=3)),
    Claim("distance-noise", "Under distance noise the baseline's accuracy drops much more than "
          "3DMPE's.", "Sec. 'Robustness', Fig. gaussian_noise", "paper-noise-distance",
          partial(degrades_less, factor=2.0)),
    Claim("distance-noise-above", "(implied) Under distance noise the baseline stays less accurate "
          "than 3DMPE.", "Sec. 'Robustness', Fig. gaussian_noise", "paper-noise-distance",
          partial(stays_above)),
    Claim("correspondence-noise", "3DMPE is robust to erroneous correspondences; the baseline "
          "degrades more.", "Sec. 'Robustness', Fig. perm_noise", "paper-noise-correspondence",
          partial(degrades_less, factor=2.0)),
    Claim("correspondence-noise-above", "(implied) Under wrong correspondences the baseline stays "
          "less accurate than 3DMPE.", "Sec. 'Robustness', Fig. perm_noise",
          "paper-noise-correspondence", partial(stays_above)),
    Claim("runtime-linear-k", "With variable projections, runtime increases linearly in the number "
          "of viewpoints.", "Sec. 'Scalability', Fig. viewpoints_var_Run_Time", "paper-views",
          partial(linear_runtime, setting="variable")),
    Claim("runtime-linear-k-per-iteration", "(the same, per iteration) With variable projections, "
          "an iteration's time increases linearly in the number of viewpoints.",
          "Sec. 'Scalability', Fig. viewpoints_var_Run_Time", "paper-views",
          partial(linear_runtime, setting="variable", measure="iteration")),
    Claim("runtime-flat-k", "With fixed projections, the effect of more projections on runtime is "
          "negligible.", "Sec. 'Scalability', Fig. viewpoints_fixed_Run_Time", "paper-views",
          partial(flat_runtime, setting="fixed")),
    Claim("runtime-flat-k-per-iteration", "(the same, per iteration) With fixed projections, more "
          "projections barely change an iteration's time.",
          "Sec. 'Scalability', Fig. viewpoints_fixed_Run_Time", "paper-views",
          partial(flat_runtime, setting="fixed", measure="iteration")),
    Claim("raytrace-three-views", "With only 5 projections, most points are present in at least 3 "
          "viewpoints.", "Sec. 'Scalability', Fig. raytrace_visible", "paper-raytrace-counts",
          partial(most_in_three_views), solvers=("any",)),
    Claim("colmap-fails-below-200", "COLMAP often failed to initialize reliably when fewer than "
          "200 images were used.", "Sec. 'Exploratory Integration with COLMAP'", "paper-colmap",
          partial(colmap_fails_below), solvers=("any",)),
    Claim("ours-faster", "(ours) refine reaches at least 3DMPE's accuracy, at least 5× faster.",
          "mpe3d, not the paper", "paper-points", partial(faster_and_as_exact), solvers=("refine",)),
)

VERDICT_COLUMNS = {"sgd": "3DMPE (paper)", "refine": "ours (refine)"}
METHOD_CLAIM = Claim.__dataclass_fields__["solvers"].default  # a claim about the method itself


def verdict_columns(added: tuple[str, ...] = ()) -> dict[str, str]:
    """solver -> its verdict column: the paper's method, ours, and each added one."""
    from mpe3d.reports.load import method_label

    return {**VERDICT_COLUMNS, **{name: method_label(name) for name in added}}


def check(claim: Claim, frame: pd.DataFrame, added: tuple[str, ...] = ()) -> dict[str, Verdict]:
    """The claim's verdict for each solver column (n/a where it does not apply)."""
    out = {}
    for solver, column in verdict_columns(added).items():
        if "any" in claim.solvers and solver == "sgd":
            out[column] = claim.check(frame, None)
        elif solver in claim.solvers or (solver in added and claim.solvers == METHOD_CLAIM):
            out[column] = claim.check(frame, solver)
        else:
            out[column] = Verdict(NOT_APPLICABLE)
    return out


def runs_per_group(frame: pd.DataFrame, varying) -> int:
    """How many runs (shapes × repeats) stand behind each setting a claim
    compares: the median count over the groups of every other varying key."""
    keys = [k for k in varying if k in frame and k not in ("shape", "seed")]
    if frame.empty:
        return 0
    if not keys:
        return len(frame)
    return int(frame.groupby(keys, dropna=False).size().median())


def claims_table(frames: dict[str, pd.DataFrame], claims=CLAIMS,
                 full_sizes: dict[str, int] | None = None, added: tuple[str, ...] = ()) -> pd.DataFrame:
    """One row per claim: the claim, where, the test, and each verdict with its numbers.

    ``frames`` maps experiment names to their runs; a missing experiment
    counts as no runs. ``full_sizes`` gives, per experiment, the runs per
    group at the full scale: a verdict from fewer is marked provisional.
    ``added`` solvers (plug-ins) get a verdict column each, on the claims
    about the method itself.
    """
    from mpe3d.reports.load import varying_columns

    rows = []
    for claim in claims:
        frame = frames.get(claim.experiment, pd.DataFrame())
        row = {"claim": claim.statement, "paper": claim.source, "experiment": claim.experiment,
               "test": claim.test}
        full = (full_sizes or {}).get(claim.experiment)
        done = frame[frame["status"] == "FINISHED"] if "status" in frame else frame
        have = runs_per_group(done, varying_columns(done)) if full and len(done) else None
        for column, verdict in check(claim, frame, tuple(added)).items():
            row[column] = verdict.verdict
            if have is not None and have < full and verdict.verdict in (HOLDS, FAILS):
                row[column] += f", provisional ({have} runs per group; the full scale has {full})"
            row[f"{column}: numbers"] = verdict.numbers
            row[f"{column}: runs"] = verdict.runs
        rows.append(row)
    return pd.DataFrame(rows)


MARKS = {HOLDS: "✓ holds", FAILS: "✗ fails", NOT_ENOUGH: "… too few runs", NOT_APPLICABLE: "–"}


def _mark(verdict: str) -> str:
    base, provisional = verdict.split(",")[0], "provisional" in verdict
    return MARKS.get(base, base) + (" (provisional)" if provisional else "")


def claim_lines(table: pd.DataFrame) -> tuple[pd.DataFrame, list[list[tuple[str, str]]]]:
    """:func:`claims_table` read at a glance: one line per claim (the claim, a
    mark per method, the headline number: the first clause of the first
    method's numbers), and what each line folds away (where, the test, every
    method's verdict with its numbers and runs)."""
    lines, details = [], []
    columns = [c for c in table.columns if f"{c}: numbers" in table.columns]
    for _, row in table.iterrows():
        numbers = [row[f"{c}: numbers"] for c in columns if row[f"{c}: numbers"]]
        lines.append({"claim": row["claim"], **{c: _mark(row[c]) for c in columns},
                      "headline": numbers[0].split(";")[0] if numbers else ""})
        details.append([("where", f"{row['paper']} (experiment {row['experiment']})"),
                        ("test", row["test"])]
                       + [(c, f"{row[c]}: {row[f'{c}: numbers'] or 'no numbers'} "
                              f"({row[f'{c}: runs']} runs)")
                          for c in columns if row[c] != NOT_APPLICABLE])
    return pd.DataFrame(lines), details
