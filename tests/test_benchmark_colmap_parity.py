"""benchmarks/colmap_parity.py: a thin front of the photos sweep, one JSON line per tracked run."""
import json
import os
import subprocess
import sys

import pytest

from tests.helpers import REPO


@pytest.mark.slow
def test_the_parity_benchmark_runs_the_photos_sweep_and_prints_its_tracked_runs(tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
           "XDG_CACHE_HOME": str(tmp_path / "cache"), "PYTHONWARNINGS": "ignore"}
    command = [sys.executable, str(REPO / "benchmarks" / "colmap_parity.py"), "--shapes", "chair", "--sizes", "8",
               "--seeds", "0", "--jobs", "1"]
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert "machine" in lines[0]
    runs = lines[1:]
    assert sorted(r["photos.solver"] for r in runs) == ["bundle", "colmap", "colmap_global"]
    assert all(r["status"] == "FINISHED" and 0 <= r["pose_auc3"] <= 100 for r in runs)
    assert sum(r["features_cached"] for r in runs) == 2  # one extraction, shared by the three methods
    # (that a rerun computes nothing is the sweep's own: test_photos_pipeline)
