"""Claim checks on hand-made run tables: every verdict, with the numbers behind it."""
import itertools

import numpy as np
import pandas as pd
import pytest

from mpe3d.reports.claims import (CLAIMS, FAILS, HOLDS, NOT_APPLICABLE, NOT_ENOUGH, claims_table,
                            degrades_less, flat_runtime, good_where, linear_runtime,
                            most_in_three_views, smart_beats_random)


def runs(rows):
    """A run table as reports.load.runs returns it (FINISHED unless told)."""
    frame = pd.DataFrame(rows)
    if "status" not in frame:
        frame["status"] = "FINISHED"
    return frame


def init_runs(random_cd, smart_cd, repeats=2):
    return runs([{"solver.name": "sgd", "shape": shape, "projections": setting, "init": init,
                  "cd_x100": cd, "seed": seed}
                 for shape, setting, seed in itertools.product(["chair", "car"], ["fixed", "variable"],
                                                               range(repeats))
                 for init, cd in (("random", random_cd), ("smart", smart_cd))])


def test_smart_init_verdicts():
    assert smart_beats_random(init_runs(3.0, 0.1), "sgd", factor=5).verdict == HOLDS
    verdict = smart_beats_random(init_runs(0.3, 0.1), "sgd", factor=5)
    assert verdict.verdict == FAILS and "geometric mean 3×" in verdict.numbers
    only_smart = init_runs(3.0, 0.1)
    only_smart = only_smart[only_smart["init"] == "smart"]
    assert smart_beats_random(only_smart, "sgd", factor=5).verdict == NOT_ENOUGH
    failed = init_runs(3.0, 0.1).assign(status="FAILED")
    assert smart_beats_random(failed, "sgd", factor=5).verdict == NOT_ENOUGH


def level_runs(column, levels, cd, solver="sgd"):
    return runs([{"solver.name": solver, column: level, "projections": setting,
                  "cd_x100": cd(level), "seed": seed}
                 for level, setting, seed in itertools.product(levels, ["fixed", "variable"], range(3))])


def test_good_where_selects_levels_and_names_the_worst():
    frame = level_runs("visibility.k", range(1, 8), lambda k: 5.0 if k < 3 else 0.01 * k)
    check = dict(column="visibility.k", at_least=3)
    assert good_where(frame, "sgd", **check).verdict == HOLDS  # k = 1, 2 are bad but not claimed
    worse = level_runs("visibility.k", range(1, 8), lambda k: 0.5 if k == 4 else 0.01)
    verdict = good_where(worse, "sgd", **check)
    assert verdict.verdict == FAILS and "worst 0.5 at visibility.k=4" in verdict.numbers
    assert good_where(level_runs("visibility.k", [1, 2], lambda k: 0.01), "sgd", **check).verdict == NOT_ENOUGH
    points = level_runs("points", [128, 256], lambda n: 0.01)
    assert good_where(points, "sgd", column="points", min_levels=3).verdict == NOT_ENOUGH
    assert good_where(frame, "sgd", column="visibility.k", among=(4, 5)).verdict == HOLDS
    assert good_where(frame, "refine", **check).verdict == NOT_ENOUGH  # no refine runs


def noise_runs(method_rise, baseline_rise, fractions=(0.0, 0.3, 0.9)):
    rows = []
    for p, q, solver, seed in itertools.product([0.05, 0.1], fractions, ["sgd", "baseline"], range(2)):
        start, rise = (0.01, method_rise) if solver == "sgd" else (1.0, baseline_rise)
        rows.append({"solver.name": solver, "noise.amplitude": p, "noise.fraction": q,
                     "cd_x100": start + rise * q / max(fractions), "seed": seed})
    return runs(rows)


def test_degrades_less_compares_rises_per_amplitude():
    assert degrades_less(noise_runs(0.1, 2.0), "sgd", factor=2).verdict == HOLDS
    verdict = degrades_less(noise_runs(1.5, 2.0), "sgd", factor=2)
    assert verdict.verdict == FAILS and "p=0.05" in verdict.numbers and "p=0.1" in verdict.numbers
    assert degrades_less(noise_runs(0.1, 2.0, fractions=(0.0, 0.2)), "sgd", factor=2).verdict == NOT_ENOUGH
    no_baseline = noise_runs(0.1, 2.0)
    no_baseline = no_baseline[no_baseline["solver.name"] == "sgd"]
    assert degrades_less(no_baseline, "sgd", factor=2).verdict == NOT_ENOUGH


def runtime_runs(runtime, views=range(2, 9), setting="variable"):
    return runs([{"solver.name": "sgd", "views": k, "projections": setting, "runtime_s": runtime(k),
                  "seed": seed} for k in views for seed in range(2)])


def test_runtime_claims():
    assert linear_runtime(runtime_runs(lambda k: 0.5 * k + 1), "sgd").verdict == HOLDS
    verdict = linear_runtime(runtime_runs(lambda k: 10.0 if k % 2 else 1.0), "sgd")
    assert verdict.verdict == FAILS and "R²" in verdict.numbers
    assert linear_runtime(runtime_runs(lambda k: k, views=[2, 3, 4]), "sgd").verdict == NOT_ENOUGH
    fixed = runtime_runs(lambda k: 1.0 + 0.01 * k, setting="fixed")
    assert flat_runtime(fixed, "sgd").verdict == HOLDS
    assert flat_runtime(runtime_runs(lambda k: k, setting="fixed"), "sgd").verdict == FAILS


def test_raytrace_share():
    frame = runs([{"solver.name": "sgd", "shape": s, "points": 100, "seen_ge_3": n}
                  for s, n in (("chair", 70), ("sofa", 60))])
    assert most_in_three_views(frame, None).verdict == HOLDS
    frame.loc[1, "seen_ge_3"] = 20
    verdict = most_in_three_views(frame, None)
    assert verdict.verdict == FAILS and "sofa 20%" in verdict.numbers


def test_claims_table_covers_every_claim_and_marks_what_does_not_apply():
    table = claims_table({"paper-smart-init": init_runs(3.0, 0.1)})
    assert len(table) == len(CLAIMS) >= 7
    smart = table[table["experiment"] == "paper-smart-init"].iloc[0]
    assert smart["3DMPE (paper)"] == HOLDS and smart["ours (refine)"] == NOT_APPLICABLE
    assert smart["3DMPE (paper): runs"] == 16
    others = table[table["experiment"] != "paper-smart-init"]
    assert set(others["3DMPE (paper)"]) <= {NOT_ENOUGH, NOT_APPLICABLE}


@pytest.mark.parametrize("claim", CLAIMS, ids=lambda c: c.id)
def test_every_claim_says_not_enough_on_an_empty_table(claim):
    for solver in claim.solvers:
        assert claim.check(pd.DataFrame(), None if solver == "any" else solver).verdict == NOT_ENOUGH
    assert np.all([claim.statement, claim.source, claim.test, claim.experiment])


def test_claim_tests_are_written_from_their_thresholds():
    from functools import partial

    from mpe3d.reports.claims import Claim

    claim = Claim("x", "s", "src", "paper-views", partial(good_where, column="views", among=(4, 5),
                                                           threshold=0.3))
    assert claim.test == "median CD <= 0.3 for views in {4, 5}, both settings"
    stricter = Claim("y", "s", "src", "paper-noise-distance", partial(degrades_less, factor=3.5))
    assert "is >= 3.5× the method's" in stricter.test


def test_verdicts_from_fewer_runs_than_the_full_scale_are_provisional():
    frame = init_runs(3.0, 0.1, repeats=2)  # 2 shapes × 2 repeats per (setting, init)
    table = claims_table({"paper-smart-init": frame}, full_sizes={"paper-smart-init": 16})
    smart = table[table["experiment"] == "paper-smart-init"].iloc[0]
    assert smart["3DMPE (paper)"] == f"{HOLDS}, provisional (4 runs per group; the full scale has 16)"
    same = claims_table({"paper-smart-init": frame}, full_sizes={"paper-smart-init": 4})
    assert same[same["experiment"] == "paper-smart-init"].iloc[0]["3DMPE (paper)"] == HOLDS
