"""Reconstruct from 2D coordinates at scale, one JSON line per case.

    python benchmarks/reconstruct_scale.py [--points 100000] [--points 1000000] [--views 8]

Each point is in exactly 3 of the views, noise-free, fed through the public
API (``mpe3d.reconstruct``, validation included): by default as keypoints pose
it, bundle adjustment (``--objective reprojection``), or the 3DMPE stress
solved by refine (``--objective stress``).
Targets: 100,000 points x 8 views, roa < 1e-6 in under 60 s and 4 GB;
1,000,000 points x 8 views, roa < 1e-6 in under 60 s and 2 GB, both settings
and both objectives.
Peak memory is this process's maximum RSS (ru_maxrss), scene sampling
included, so it is an upper bound on the solver's.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

from mpe3d import make_config, reconstruct
from mpe3d.harness.scene.metrics import roa
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams


def case(points: int, views: int, setting: str, shape: str, objective: str) -> dict:
    config = make_config({"shape": shape, "points": points, "views": views, "observe": "coordinates",
                          "projections": setting})
    streams = seed_streams(0)
    scene = build_scene(config, streams)
    obs, _ = observe(scene, config, streams)
    data = [{"ids": v.ids, "xy": v.coordinates} for v in obs.views]
    start = time.perf_counter()
    result = reconstruct(data, projections=scene.rotations if setting == "fixed" else None,
                         objective=objective)
    wall = time.perf_counter() - start
    limit_gb = 4 if points <= 100_000 else 2
    error = roa(result.points, scene.points[result.ids])
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    return {"benchmark": "reconstruct_scale", "points": points, "views": views, "setting": setting,
            "shape": shape, "wall_s": round(wall, 2), "solver_s": round(result.report["runtime_s"], 2),
            "objective": objective, "camera": result.report.get("camera"),
            "roa": error, "peak_rss_gb": round(peak_gb, 2),
            "stress_pairs": result.report.get("stress_pairs"),
            "target": f"roa < 1e-6, < 60 s, < {limit_gb} GB",
            "within_target": bool(error < 1e-6 and wall < 60 and peak_gb < limit_gb)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, action="append")
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--setting", choices=("variable", "fixed"), action="append")
    parser.add_argument("--shape", default="chair")
    parser.add_argument("--objective", choices=("reprojection", "stress"), default="reprojection")
    args = parser.parse_args()
    for n in args.points or [100_000]:
        for setting in args.setting or ["variable", "fixed"]:
            print(json.dumps(case(n, args.views, setting, args.shape, args.objective)), flush=True)


if __name__ == "__main__":
    main()
