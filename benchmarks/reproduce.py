"""Wall time of ``mpe3d reproduce-paper`` from an empty store, one JSON line per scale.

    python benchmarks/reproduce.py [--scale quick] [--scale full] [--jobs 2] [--keep DIR]

Each scale runs the installed ``mpe3d reproduce-paper`` in a fresh folder
(a new SQLite store, so nothing is reused), then once more to time the
resume, which must run nothing. Targets on 2 cores: quick < 180 s, full
< 900 s (the paper's sizes with the paper's SGD). ``--keep DIR`` leaves each
scale's store and reports in DIR/SCALE instead of a temporary folder.
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

TARGETS_S = {"tiny": 60.0, "quick": 180.0, "full": 900.0}


def mpe3d() -> list[str]:
    script = Path(sys.executable).parent / "mpe3d"
    return [str(script)] if script.exists() else [sys.executable, "-m", "mpe3d.harness.cli"]


def reproduce(folder: Path, scale: str, jobs: int, out: str) -> tuple[float, str]:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    start = time.perf_counter()
    done = subprocess.run([*mpe3d(), "reproduce-paper", "--scale", scale, "--jobs", str(jobs),
                           "--out", out, "--quiet"], cwd=folder, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode not in (0, 1):
        sys.exit(f"reproduce-paper failed ({done.returncode}): {done.stderr.strip()}")
    return wall, (folder / out / "index.md").read_text()


def case(scale: str, jobs: int, keep: Path | None) -> dict:
    with tempfile.TemporaryDirectory(prefix="mpe3d-reproduce-") as tmp:
        folder = Path(tmp) if keep is None else keep / scale
        folder.mkdir(parents=True, exist_ok=True)
        if any(folder.iterdir()):
            sys.exit(f"--keep: {folder} is not empty; the timing must start from an empty store")
        wall, index = reproduce(folder, scale, jobs, "report")
        resume, again = reproduce(folder, scale, jobs, "again")
    runs = re.search(r"(\d+) runs in (\d+) experiments: (\d+) run now", index)
    rerun = re.search(r"(\d+) run now, (\d+) reused", again)
    failed = sum(int(n) for n in re.findall(r"(\d+) failed,", index))
    return {"benchmark": "reproduce-paper", "scale": scale, "jobs": jobs, "cpus": os.cpu_count(),
            "runs": int(runs.group(1)), "failed_runs": failed, "wall_s": round(wall, 1),
            "target_s": TARGETS_S[scale], "within_target": wall < TARGETS_S[scale],
            "resume_wall_s": round(resume, 1), "resume_ran": int(rerun.group(1)),
            "python": platform.python_version(), "load_avg_1min": round(os.getloadavg()[0], 2)}


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
