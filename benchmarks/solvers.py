"""Solver benchmark: one JSON line per (N, K, setting, solver) case.

    python benchmarks/solvers.py [--points 512 1024 2048] [--views 5] [--shape chair]

Each case builds one noise-free scene (each point in exactly 3 views), runs
every solver on the same observations, and prints its runtime (the solver
alone, smart start included), iterations and metrics. Compare solvers by
ratios within one run: absolute seconds depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path

# Run as a script, this file's folder comes first on sys.path and its name
# would shadow the ``solvers`` package.
if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
    sys.path.pop(0)

from harness.config import make_config
from harness.execute import run


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, nargs="+", default=[512, 1024, 2048])
    parser.add_argument("--views", type=int, nargs="+", default=[5])
    parser.add_argument("--shape", default="chair")
    parser.add_argument("--solvers", nargs="+", default=["baseline", "sgd"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for N in args.points:
        for K in args.views:
            for setting in ("fixed", "variable"):
                for solver in args.solvers:
                    config = make_config({"shape": args.shape, "points": N, "views": K,
                                          "visibility.mode": "exact", "visibility.k": 3,
                                          "projections": setting, "solver": solver,
                                          "seed": args.seed})
                    result = run(config)
                    m = result.metrics
                    print(json.dumps({
                        "benchmark": "solvers", "shape": args.shape, "N": N, "K": K,
                        "setting": setting, "solver": solver,
                        "runtime_s": round(m["runtime_s"], 4), "iterations": m["iterations"],
                        "termination": result.reconstruction.termination,
                        "stress": m["stress"], "roa": m["roa"], "cd_mean": m["cd_mean"],
                        "emd_mean": m["emd_mean"], "python": platform.python_version(),
                    }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
