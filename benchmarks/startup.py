"""Start-up benchmark: how long the command line takes to answer ``--help``,
and how long a fresh process takes to reach its first solve.

    python benchmarks/startup.py [--repeats 7]

One JSON line per command (``mpe3d --help``, ``mpe3d run --help``): the median
and the worst wall time of ``--repeats`` fresh processes, beside the time of a
bare ``python -c pass`` measured in the same run (the floor no command beats),
with the machine's load average. Target: under 1 s each.

A last line times ``mpe3d run`` of the paper's default scene (airplane,
N = 1024, K = 5, SGD) as a fresh process: its wall time, the run's own
``runtime_s`` (the solver) and their difference, what a process spends
besides solving (imports, the code identity, loading the compiled kernels,
sampling and scoring). The kernels are compiled before the first timing, as
they are once per install. Target: the difference under 2 s.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time


def wall(command: list[str], repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return sorted(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    beside = os.path.join(os.path.dirname(sys.executable), "mpe3d")  # this environment's first
    script = beside if os.path.exists(beside) else shutil.which("mpe3d")
    floor = wall([sys.executable, "-c", "pass"], args.repeats)
    for words in (["--help"], ["run", "--help"]):
        times = wall([script, *words], args.repeats)
        median = times[len(times) // 2]
        print(json.dumps({"benchmark": "startup", "command": " ".join(["mpe3d", *words]),
                          "median_s": round(median, 3), "worst_s": round(times[-1], 3),
                          "python_floor_s": round(floor[len(floor) // 2], 3),
                          "met": median < 1.0, "load_avg_1min": round(os.getloadavg()[0], 2)}),
              flush=True)
    print(json.dumps(first_solve(script, args.repeats)), flush=True)
    return 0


def first_solve(script: str, repeats: int) -> dict:
    command = [script, "run", "shape=airplane", "points=1024", "views=5", "solver=sgd", "--json"]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)  # compiles the kernels once
    walls, solves = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        walls.append(time.perf_counter() - start)
        solves.append(json.loads(out)["runtime_s"])
    besides = sorted(w - s for w, s in zip(walls, solves))
    median = besides[len(besides) // 2]
    return {"benchmark": "startup", "command": " ".join(["mpe3d", *command[1:]]),
            "wall_median_s": round(sorted(walls)[len(walls) // 2], 3),
            "solve_median_s": round(sorted(solves)[len(solves) // 2], 3),
            "besides_solving_median_s": round(median, 3), "met": median < 2.0,
            "load_avg_1min": round(os.getloadavg()[0], 2)}


if __name__ == "__main__":
    raise SystemExit(main())
