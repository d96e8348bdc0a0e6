"""The quick reproduction's runs keep their identities: the config hashes of
every paper sweep at scale quick, as a store made on 2026-12-07 (code 46add80,
before a run's MLflow params became the keys that shaped it) recorded them
(``tests/data/quick_config_hashes.json``). A change that means to move them
rewrites that file in a commit that says why: every tracked run would be
computed again."""

from __future__ import annotations

import json
from pathlib import Path

from mpe3d.harness.experiment.sweep import load_sweep
from mpe3d.sweeps import paper_sweeps

RECORDED = Path(__file__).resolve().parents[2] / "data" / "quick_config_hashes.json"


def test_the_quick_reproductions_config_hashes_are_those_recorded():
    recorded = json.loads(RECORDED.read_text())
    now: dict[str, set[str]] = {}
    for path in paper_sweeps():
        sweep = load_sweep(path, "quick")
        now.setdefault(sweep.name, set()).update(config.hash() for config in sweep.runs)
    assert sorted(now) == sorted(recorded)
    for name, hashes in now.items():
        assert hashes == set(recorded[name]), name
