"""Start-up benchmark: how long the command line takes to answer ``--help``,
and how long a fresh process takes to reach its first solve.

    python benchmarks/startup.py [--repeats 7]

One JSON line per command (``mpe3d --help``, ``mpe3d run --help``): the median
and the worst wall time of ``--repeats`` fresh processes, beside the time of a
bare ``python -c pass`` measured in the same run (the floor no command beats),
with the machine's load average. Target: under 1 s each.

A last line times ``mpe3d run shape=airplane points=512 views=4
solver=refine`` as a fresh process: its wall time, the run's own
``runtime_s`` (the solver) and their difference, what a process spends
besides solving (imports, the code identity, loading the compiled kernels,
sampling and scoring), and when the process reached its first solve:
the time from starting it to the solver's call (read by a probe that wraps
``mpe3d.solvers.solve`` in the fresh process and prints the clock there).
The kernels are compiled before the first timing, as they are once per
install. Targets: the first solve within 2 s of the start, and the
difference (which also holds scoring, the exact EMD among it) at most 1.5 s,
on the machine that ``machine`` describes (``benchmarks/machine.py``,
measured first, on an idle machine).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

from machine import describe

BESIDES_TARGET_S = 1.5

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
    machine = describe()  # before the timings, on an idle machine
    floor = wall([sys.executable, "-c", "pass"], args.repeats)
    for words in (["--help"], ["run", "--help"]):
        times = wall([script, *words], args.repeats)
        median = times[len(times) // 2]
        print(json.dumps({"benchmark": "startup", "command": " ".join(["mpe3d", *words]),
                          "median_s": round(median, 3), "worst_s": round(times[-1], 3),
                          "python_floor_s": round(floor[len(floor) // 2], 3),
                          "met": median < 1.0, "load_avg_1min": round(os.getloadavg()[0], 2)}),
              flush=True)
    print(json.dumps({**first_solve(script, args.repeats), "machine": machine}), flush=True)
    return 0


# Runs the command line as ``mpe3d`` would, with the solver entry point
# wrapped to print the wall clock (time.time, comparable across processes)
# on stderr at its first call.
PROBE = """
import sys, time
import mpe3d.solvers as solvers
solve = solvers.solve
def first(*args, **kwargs):
    if not getattr(first, "said", False):
        first.said = True
        print(f"FIRST_SOLVE {time.time():.6f}", file=sys.stderr, flush=True)
    return solve(*args, **kwargs)
solvers.solve = first
from mpe3d.cli import console
sys.argv = ["mpe3d", *sys.argv[1:]]
raise SystemExit(console())
"""


def first_solve(script: str, repeats: int) -> dict:
    words = ["run", "shape=airplane", "points=512", "views=4", "solver=refine", "--json"]
    command = [script, *words]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)  # compiles the kernels once
    walls, solves, reached = [], [], []
    for _ in range(repeats):
        start = time.perf_counter()
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        walls.append(time.perf_counter() - start)
        solves.append(json.loads(out)["runtime_s"])
        began = time.time()
        err = subprocess.run([sys.executable, "-c", PROBE, *words], check=True,
                             capture_output=True, text=True).stderr
        reached.append(float(err.split("FIRST_SOLVE ")[1].split()[0]) - began)
    besides = sorted(w - s for w, s in zip(walls, solves))
    median = besides[len(besides) // 2]
    first = sorted(reached)[len(reached) // 2]
    return {"benchmark": "startup", "command": " ".join(["mpe3d", *words]),
            "wall_median_s": round(sorted(walls)[len(walls) // 2], 3),
            "solve_median_s": round(sorted(solves)[len(solves) // 2], 3),
            "first_solve_median_s": round(first, 3), "first_solve_met": first < 2.0,
            "besides_solving_median_s": round(median, 3), "met": median <= BESIDES_TARGET_S,
            "load_avg_1min": round(os.getloadavg()[0], 2)}


if __name__ == "__main__":
    raise SystemExit(main())
