"""Ctrl-C, twice, SIGINT and SIGTERM stop a real sweep the same way: exit 130
within 10 s, the one line last, no process left, and a rerun that completes
every config exactly once. ``scripts/interrupt_trials.py`` runs many trials."""
import random

import pytest

from tests.harness.interrupts import MOMENTS, check, trial


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_ctrl_c_mid_run_stops_cleanly_and_the_rerun_completes(tmp_path):
    check(trial(tmp_path, "running", random.Random(0), how="group-sigint", repeats=24))
    assert not (tmp_path / "mpe3d-journal").exists()  # emptied and tidied away


@pytest.mark.slow
@pytest.mark.parametrize("moment,how", zip(MOMENTS, ("double-sigint", "sigterm", "group-sigint",
                                                     "double-sigint")))
def test_every_moment_and_every_way_to_stop(tmp_path, moment, how):
    """Each moment once, each way to stop at least once (the many-trial
    measurement is scripts/interrupt_trials.py)."""
    # "running" waits for the first logged run, then up to 1.5 s more: 16 runs were
    # over in 1.8 s of that on this machine, so the signal sometimes found the
    # sweep finished (too late) or finalising (exit 130, then loky's tracker warned)
    repeats = 48 if moment == "running" else 16
    check(trial(tmp_path, moment, random.Random(f"{moment} {how}"), how=how, repeats=repeats))
