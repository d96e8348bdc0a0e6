"""Solver benchmark: sgd vs factorize vs refine, one JSON line per (case, solver).

    python benchmarks/solvers.py [--points 512 2048 8192] [--views 4 5 8]
        [--shapes chair airplane table] [--noise none distance:0.2:0.05 ...]
        [--solvers sgd factorize refine refine:huber refine:soft_l1] [--sgd-max-points 2048]

A solver written ``refine:LOSS`` is refine with that loss; its line carries its
time over refine's (l2) in the same case.
Each case builds one scene (each point in exactly 3 views) and hands the same
observations to every solver. A line holds the solver's runtime, iterations,
metrics, its speed-up over sgd measured in the same run, and its peak memory
(with --memory: tracemalloc, numpy included) next to the size of the largest input distance
matrix and of an N x N matrix. After the cases, one summary line per target:
(a) worst noise-free ROA, (b) refine's speed-up over sgd at N=2048, K=4,
(c) median CD of refine vs sgd per noise case, (d) peak memory at the largest N.
Compare ratios within one run: absolute seconds depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import tracemalloc
import warnings
from collections import defaultdict

import numpy as np

from mpe3d import make_config, solvers
from mpe3d.harness.scene.metrics import evaluate
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams

NOISE = ["none", "distance:0.2:0.05", "distance:0.2:0.1", "distance:0.4:0.05", "distance:0.4:0.1",
         "correspondence:0.2:0.05", "correspondence:0.2:0.1", "correspondence:0.4:0.05",
         "correspondence:0.4:0.1"]


def noise_keys(spec: str) -> dict:
    if spec == "none":
        return {"noise.type": "none"}
    kind, q, p = spec.split(":")
    return {"noise.type": kind, "noise.fraction": float(q), "noise.amplitude": float(p)}


def measure(name: str, obs, scene, seed: int, memory: bool) -> dict:
    if memory:  # tracemalloc slows numpy down: off for timing runs
        tracemalloc.start()
    name, _, loss = name.partition(":")
    options = {"loss": loss} if loss else {}
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = solvers.solve(name, obs, random_state=seed, **options)
    seconds = time.perf_counter() - start
    out = {}
    if memory:
        out["solver_peak_mb"] = round(tracemalloc.get_traced_memory()[1] / 2**20, 1)
        tracemalloc.stop()
    metrics, _ = evaluate(scene.points, rec.points, "rigid", np.random.default_rng(seed))
    return {"runtime_s": round(seconds, 4), "solve_s": round(rec.runtime_s, 4),
            "iterations": rec.iterations,
            "ms_per_iteration": round(1e3 * rec.runtime_s / max(rec.iterations, 1), 3),
            "termination": rec.termination, "stress": rec.stress, "roa": metrics["roa"],
            "cd": metrics["cd"], "cd_mean": metrics["cd_mean"], "emd_mean": metrics["emd_mean"],
            **out}


def main(argv=None) -> int:
    from mpe3d.solvers import warmup

    warmup.warm()  # once per process, as a sweep's worker does: no case pays it
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, nargs="+", default=[512, 2048, 8192])
    parser.add_argument("--views", type=int, nargs="+", default=[4, 5, 8])
    parser.add_argument("--shapes", nargs="+", default=["chair"])
    parser.add_argument("--settings", nargs="+", default=["fixed", "variable"])
    parser.add_argument("--noise", nargs="+", default=NOISE)
    parser.add_argument("--solvers", nargs="+", default=["sgd", "factorize", "refine"])
    parser.add_argument("--sgd-max-points", type=int, default=2048,
                        help="skip sgd above this N (at N=8192 one sgd run takes many minutes)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--memory", action="store_true",
                        help="also record each solver's peak memory (tracemalloc; slows numpy)")
    args = parser.parse_args(argv)
    rows = []
    for N in args.points:
        for K in args.views:
            for setting in args.settings:
                for noise in args.noise:
                    for shape in args.shapes:
                        config = make_config({"shape": shape, "points": N, "views": K,
                                              "visibility.mode": "exact", "visibility.k": 3,
                                              "projections": setting, "seed": args.seed,
                                              **noise_keys(noise)})
                        streams = seed_streams(args.seed)
                        scene = build_scene(config, streams)
                        obs, _ = observe(scene, config, streams)
                        largest = max(v.size for v in obs.views)
                        sgd_time = refine_time = None
                        for name in args.solvers:
                            if name == "sgd" and N > args.sgd_max_points:
                                continue
                            row = {"benchmark": "solvers", "shape": shape, "N": N, "K": K,
                                   "setting": setting, "noise": noise, "solver": name,
                                   **measure(name, obs, scene, args.seed, args.memory),
                                   "largest_input_matrix_mb": round(8 * largest ** 2 / 2**20, 1),
                                   "n_by_n_mb": round(8 * N * N / 2**20, 1)}
                            if name == "sgd":
                                sgd_time = row["runtime_s"]
                            elif sgd_time:
                                row["speedup_vs_sgd"] = round(sgd_time / row["runtime_s"], 1)
                            if name == "refine":
                                refine_time = row["runtime_s"]
                            elif name.startswith("refine:") and refine_time:
                                row["time_over_l2"] = round(row["runtime_s"] / refine_time, 2)
                            row["python"] = platform.python_version()
                            rows.append(row)
                            print(json.dumps(row), flush=True)
    for line in summaries(rows):
        print(json.dumps(line), flush=True)
    return 0


def summaries(rows: list[dict]) -> list[dict]:
    """One line per target of the fast-solvers issue, from this run's rows."""
    out = []
    clean = [r for r in rows if r["noise"] == "none" and r["solver"] != "sgd"]
    if clean:
        worst = defaultdict(float)
        for r in clean:
            worst[f"{r['solver']}/{r['setting']}"] = max(worst[f"{r['solver']}/{r['setting']}"], r["roa"])
        out.append({"target": "a: noise-free roa < 1e-8", "worst_roa": dict(worst),
                    "met": all(v < 1e-8 for v in worst.values())})
    speed = [r["speedup_vs_sgd"] for r in rows if r["solver"] == "refine" and r["N"] == 2048
             and r["K"] == 4 and r["noise"] == "none" and "speedup_vs_sgd" in r]
    if speed:
        out.append({"target": "b: refine >= 50x faster than sgd at N=2048, K=4",
                    "speedups": speed, "met": min(speed) >= 50})
    by_noise = defaultdict(lambda: defaultdict(list))
    for r in rows:
        if r["noise"] != "none" and r["solver"] in ("sgd", "refine"):
            by_noise[r["noise"]][r["solver"]].append(r["cd"])
    medians = {noise: {s: float(np.median(v)) for s, v in d.items()} for noise, d in by_noise.items()
               if {"sgd", "refine"} <= set(d)}
    if medians:
        out.append({"target": "c: median CD of refine <= sgd under every noise case",
                    "median_cd": medians,
                    "met": all(m["refine"] <= m["sgd"] * (1 + 1e-9) for m in medians.values())})
    robust = defaultdict(list)
    for r in rows:
        if "time_over_l2" in r:
            robust[r["solver"]].append(r["time_over_l2"])
    if robust:
        out.append({"target": "e: refine's robust losses cost <= 1.5x l2 (median over cases)",
                    "median_time_over_l2": {k: float(np.median(v)) for k, v in robust.items()},
                    "worst_time_over_l2": {k: max(v) for k, v in robust.items()},
                    "met": all(np.median(v) <= 1.5 for v in robust.values())})
    sgd = [r["ms_per_iteration"] for r in rows if r["solver"] == "sgd"]
    if sgd:
        out.append({"target": "f: sgd time per iteration (ms)", "median": float(np.median(sgd)),
                    "by_N": {N: float(np.median([r["ms_per_iteration"] for r in rows
                                                 if r["solver"] == "sgd" and r["N"] == N]))
                             for N in sorted({r["N"] for r in rows if r["solver"] == "sgd"})}})
    biggest = max((r["N"] for r in rows), default=0)
    big = [r for r in rows if r["N"] == biggest and r["solver"] != "sgd" and "solver_peak_mb" in r]
    if big:
        out.append({"target": f"d: N={biggest} without anything larger than the input matrices",
                    "peak_over_largest_input": max(r["solver_peak_mb"] / r["largest_input_matrix_mb"]
                                                   for r in big),
                    "n_by_n_mb": big[0]["n_by_n_mb"],
                    "largest_solver_peak_mb": max(r["solver_peak_mb"] for r in big)})
    return out


if __name__ == "__main__":
    sys.exit(main())
