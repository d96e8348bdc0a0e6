"""Harness overhead per run: tracking plus artifacts on SQLite, one JSON line per case.

    python benchmarks/harness_overhead.py [--runs 100] [--jobs 1]

A sweep of ``--runs`` trivially fast runs (classical MDS on 32 torus points)
goes through the real path: expansion, resume lookup, workers, MLflow logging
of params, metrics, the stress history and two PLY artifacts, then a second
invocation that finds everything done. The overhead per run is the sweep's
wall time minus the time the runs themselves took (their ``wall_s``), over
the run count. Target: <= 0.15 s per run with artifacts.

A last line times opening a new SQLite store, in this process after a first
one: made by MLflow's schema migrations (no cache folder to keep a template
in) against copied from the template MLflow made once (``--stores`` each).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from mpe3d import Tracker, load_sweep
from mpe3d.harness.runner import plan_sweeps, run_plans
from mpe3d.harness.tracking.store import store_template

TARGET_S = 0.15
SWEEP = """
name: overhead-{tag}
base: {{shape: torus, points: 32, views: 3, visibility: {{mode: exact, k: 2}},
        solver: {{name: baseline, method: classical}}}}
repeats: {runs}
"""


def case(folder: Path, runs: int, jobs: int, artifacts: bool) -> dict:
    tag = "artifacts" if artifacts else "bare"
    path = folder / f"{tag}.yaml"
    path.write_text(SWEEP.format(tag=tag, runs=runs))
    tracker = Tracker(f"sqlite:///{folder}/mlflow.db")
    start = time.perf_counter()
    plans = plan_sweeps([load_sweep(path)], tracker)
    run_plans(plans, tracker, jobs=jobs, artifacts=artifacts)
    sweep_s = time.perf_counter() - start
    frame = tracker.runs_frame(f"overhead-{tag}")
    compute_s = float(frame["wall_s"].sum())
    start = time.perf_counter()
    resumed = plan_sweeps([load_sweep(path)], tracker)
    resume_s = time.perf_counter() - start
    per_run = (sweep_s - compute_s) / runs
    return {"benchmark": "harness_overhead", "store": "sqlite", "artifacts": artifacts,
            "runs": runs, "jobs": jobs, "logged": int((frame["status"] == "FINISHED").sum()),
            "sweep_s": round(sweep_s, 3), "compute_s": round(compute_s, 3),
            "overhead_per_run_s": round(per_run, 4), "target_s": TARGET_S,
            "meets_target": per_run <= TARGET_S,
            "resume_check_s": round(resume_s, 3), "left_to_run": len(resumed[0].todo),
            "python": platform.python_version()}


def new_stores(folder: Path, count: int) -> dict:
    """Seconds to open a new store, made by MLflow and copied from the template."""
    seconds = {}
    for way, cache in (("made_by_mlflow", folder / "a-file"), ("copied", folder / "cache")):
        os.environ["XDG_CACHE_HOME"] = str(cache)  # a file: no template can be kept there
        store_template()  # made once, as the first store a user opens makes it
        start = time.perf_counter()
        for i in range(count):
            Tracker(f"sqlite:///{folder}/{way}{i}.db")
        seconds[way] = (time.perf_counter() - start) / count
    return {"benchmark": "store_open", "stores": count,
            **{f"{way}_s": round(s, 3) for way, s in seconds.items()},
            "ratio": round(seconds["made_by_mlflow"] / seconds["copied"], 1)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--stores", type=int, default=5)
    parser.add_argument("--jobs", type=int, default=1,
                        help="1 runs in this process, so the wall time is all harness and runs")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="mpe3d-bench-") as folder:
        Tracker(f"sqlite:///{folder}/mlflow.db").experiment_names()  # create the schema first
        for artifacts in (True, False):
            print(json.dumps(case(Path(folder), args.runs, args.jobs, artifacts)), flush=True)
        (Path(folder) / "a-file").write_text("")
        print(json.dumps(new_stores(Path(folder), args.stores)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
