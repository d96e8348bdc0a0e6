"""Wall time of ``mpe3d reproduce-paper`` from an empty store, one JSON line per scale.

    python benchmarks/reproduce.py [--scale quick] [--scale full] [--jobs 2] [--keep DIR]

Each scale runs the installed ``mpe3d reproduce-paper`` in a fresh folder
(a new SQLite store, so nothing is reused), then once more to time the
resume, which must run nothing. Targets on 2 cores: quick < 90 s, full
< 900 s with the colmap experiment, no run over 120 s. ``--keep DIR`` leaves
each scale's store and reports in DIR/SCALE instead of a temporary folder.

``split`` says where the time went, read back from the store: ``startup_s``
(the command's start to the first run claimed: imports, planning, the
pool's workers), ``runs_s`` (first claim to last result logged), ``report_s``
(the last result to the end: tables and figures), the workers' busy share
over ``runs_s``, and per experiment its runs' summed and longest wall time
in the workers and their summed solver time (the rest of a run's wall:
sampling, scoring, rendering and COLMAP); for colmap runs, the summed
phases. The worker wall of a run starts after its process has started and
loaded the kernels once, so a worker's start is in ``runs_s`` but in no run.
``machine`` is ``benchmarks/machine.py``'s description, measured before the
reproduction: whether the 2 cores behave as two.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from machine import describe

TARGETS_S = {"tiny": 60.0, "quick": 90.0, "full": 900.0}
LONGEST_RUN_S = 120.0
COLMAP_PHASES = ("render_s", "extract_s", "match_s", "map_s", "tracks_bundle_s", "tracks_sgd_s",
                 "tracks_refine_s")


def mpe3d() -> list[str]:
    script = Path(sys.executable).parent / "mpe3d"
    return [str(script)] if script.exists() else [sys.executable, "-m", "mpe3d.cli"]


def reproduce(folder: Path, scale: str, jobs: int, out: str) -> tuple[float, str]:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    start = time.perf_counter()
    done = subprocess.run([*mpe3d(), "reproduce-paper", "--scale", scale, "--jobs", str(jobs),
                           "--out", out, "--quiet"], cwd=folder, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode not in (0, 1):
        sys.exit(f"reproduce-paper failed ({done.returncode}): {done.stderr.strip()}")
    return wall, (folder / out / "index.md").read_text()


def split(folder: Path, started: float, ended: float, jobs: int) -> dict:
    """Where the time of the run from an empty store went (see the module doc)."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{folder / 'mlflow.db'}")
    runs = [r for e in client.search_experiments()
            for r in client.search_runs([e.experiment_id], max_results=50_000)
            if "mlflow.parentRunId" in r.data.tags]
    names = {e.experiment_id: e.name for e in client.search_experiments()}
    first = min(r.info.start_time for r in runs) / 1000
    last = max(r.info.end_time for r in runs) / 1000
    experiments: dict = {}
    for r in runs:
        m = r.data.metrics
        entry = experiments.setdefault(names[r.info.experiment_id], {
            "runs": 0, "wall_s": 0.0, "longest_s": 0.0, "solver_s": 0.0})
        entry["runs"] += 1
        entry["wall_s"] += m.get("wall_s", 0.0)
        entry["longest_s"] = max(entry["longest_s"], m.get("wall_s", 0.0))
        entry["solver_s"] += m.get("runtime_s", 0.0) if r.data.params.get("pipeline") != "colmap" else 0.0
        for phase in COLMAP_PHASES:
            if phase in m:
                entry[phase] = entry.get(phase, 0.0) + m[phase]
    busy = sum(e["wall_s"] for e in experiments.values())
    return {"startup_s": round(first - started, 1), "runs_s": round(last - first, 1),
            "report_s": round(ended - last, 1), "workers_busy_share": round(busy / (jobs * (last - first)), 3),
            "longest_run_s": round(max(e["longest_s"] for e in experiments.values()), 1),
            "experiments": {name: {k: round(v, 1) if isinstance(v, float) else v for k, v in e.items()}
                            for name, e in sorted(experiments.items(), key=lambda kv: -kv[1]["wall_s"])}}


def case(scale: str, jobs: int, keep: Path | None) -> dict:
    machine = describe()  # before the reproduction, on an idle machine
    with tempfile.TemporaryDirectory(prefix="mpe3d-reproduce-") as tmp:
        folder = Path(tmp) if keep is None else keep / scale
        folder.mkdir(parents=True, exist_ok=True)
        if any(folder.iterdir()):
            sys.exit(f"--keep: {folder} is not empty; the timing must start from an empty store")
        started = time.time()
        wall, index = reproduce(folder, scale, jobs, "report")
        where = split(folder, started, time.time(), jobs)
        resume, again = reproduce(folder, scale, jobs, "again")
    runs = re.search(r"(\d+) runs in (\d+) experiments: (\d+) run now", index)
    rerun = re.search(r"(\d+) run now, (\d+) reused", again)
    failed = sum(int(n) for n in re.findall(r"(\d+) failed,", index))
    return {"benchmark": "reproduce-paper", "scale": scale, "jobs": jobs, "cpus": os.cpu_count(),
            "runs": int(runs.group(1)), "failed_runs": failed, "wall_s": round(wall, 1),
            "target_s": TARGETS_S[scale], "within_target": wall < TARGETS_S[scale],
            "longest_run_s": where["longest_run_s"], "longest_run_target_s": LONGEST_RUN_S,
            "resume_wall_s": round(resume, 1), "resume_ran": int(rerun.group(1)), "split": where,
            "python": platform.python_version(), "load_avg_1min": round(os.getloadavg()[0], 2),
            "machine": machine}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", action="append", choices=sorted(TARGETS_S))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep each scale's store and reports in KEEP/SCALE")
    args = parser.parse_args()
    for scale in args.scale or ["quick"]:
        print(json.dumps(case(scale, args.jobs, args.keep)), flush=True)


if __name__ == "__main__":
    main()
