"""Start-up benchmark: how long the command line takes to answer ``--help``.

    python benchmarks/startup.py [--repeats 7]

One JSON line per command (``mpe3d --help``, ``mpe3d run --help``): the median
and the worst wall time of ``--repeats`` fresh processes, beside the time of a
bare ``python -c pass`` measured in the same run (the floor no command beats),
with the machine's load average. Target: under 1 s each.
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
