"""How often a solver reaches the global optimum on noise-free input.

    python benchmarks/success_rate.py [--solver sgd] [--points 512] [--seeds 3]

For every bundled and procedural shape, seed, setting (fixed, variable) and
K in {4, 5} (each point in exactly 3 views), runs the solver and counts the
runs whose ROA is below ``--threshold`` (default 1e-3 of the bounding-box
diagonal: the shape is recovered, not merely similar). Prints one JSON line
per (setting, K) with the count, the failures and the median runtime.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

from mpe3d import make_config, run
from mpe3d.harness.scene.shapes import shape_names


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--solver", default="sgd")
    parser.add_argument("--points", type=int, default=512)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--threshold", type=float, default=1e-3)
    parser.add_argument("--init", default="smart")
    args = parser.parse_args(argv)
    for setting in ("fixed", "variable"):
        for K in (4, 5):
            runs, failures, times = 0, [], []
            for shape in shape_names():
                for seed in range(args.seeds):
                    config = make_config({"shape": shape, "points": args.points, "views": K,
                                          "projections": setting, "solver": args.solver,
                                          "init": args.init, "seed": seed})
                    result = run(config)
                    runs += 1
                    times.append(result.metrics["runtime_s"])
                    if not result.metrics["roa"] < args.threshold:
                        failures.append({"shape": shape, "seed": seed,
                                         "roa": round(result.metrics["roa"], 6),
                                         "termination": result.reconstruction.termination})
            print(json.dumps({
                "benchmark": "success_rate", "solver": args.solver, "init": args.init,
                "N": args.points, "K": K, "setting": setting, "runs": runs,
                "successes": runs - len(failures), "threshold_roa": args.threshold,
                "median_runtime_s": round(statistics.median(times), 4), "failures": failures,
            }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
