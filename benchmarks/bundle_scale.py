"""Bundle adjustment with many cameras and long tracks, one JSON line per case.

    python benchmarks/bundle_scale.py [--cameras 250] [--points 3000] [--noise 0.5] [--seed 0]

The scene a new user would try: ``--cameras`` pinholes on the photo spiral
(:func:`mpe3d.harness.scene.rendering.spiral_cameras`, 400 x 400 pixels) round
``--points`` points on a sphere of radius 0.4, each point seen by a random
half of the cameras it faces (so by about 60 of 250), its keypoints with
``--noise`` px of Gaussian noise. Solved as ``mpe3d reconstruct --camera
perspective`` does, from mpe3d's own start. Each line: the wall time, the
final RMS reprojection error (px), the observations, the largest track, the
3D error after a similarity (% of the bounding-box diagonal), whether it
converged, and the machine it ran on (``benchmarks/machine.py``). Target
(issue 31): 250 cameras x 3,000 points in <= 15 s.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from machine import describe

from mpe3d import reconstruct
from mpe3d.harness.scene.metrics import similarity_transform
from mpe3d.harness.scene.rendering import spiral_cameras


def scene(n_cameras: int, n_points: int, noise: float, seed: int):
    """The views (ids, xy) and the true points."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    X = 0.4 * normals
    cams = spiral_cameras(n_cameras)
    centres = -np.einsum("kji,kj->ki", cams.rotations, cams.translations)
    facing = np.einsum("kpd,pd->kp", centres[:, None, :] - X[None], normals) > 0
    seen = facing & (rng.random(facing.shape) < 0.5)
    views = []
    for k in range(n_cameras):
        ids = np.flatnonzero(seen[k])
        x_cam = X[ids] @ cams.rotations[k].T + cams.translations[k]
        xy = cams.focal * x_cam[:, :2] / x_cam[:, 2:] + cams.width / 2
        views.append({"ids": ids, "xy": xy + noise * rng.normal(size=xy.shape), "name": f"cam{k}"})
    return views, X, seen


def similarity_error(points: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance after the best similarity, over the truth's bounding-box diagonal."""
    s, Q, t = similarity_transform(points, truth)
    rms = np.sqrt(np.mean(np.sum((s * points @ Q.T + t - truth) ** 2, axis=1)))
    return float(rms / np.linalg.norm(truth.max(axis=0) - truth.min(axis=0)))


def case(n_cameras: int, n_points: int, noise: float, seed: int) -> dict:
    views, X, seen = scene(n_cameras, n_points, noise, seed)
    machine = describe()
    start = time.perf_counter()
    result = reconstruct(views, objective="reprojection", camera="perspective",
                         principal_point=(200.0, 200.0))
    wall = time.perf_counter() - start
    report = result.report
    return {"benchmark": "bundle_scale", "cameras": n_cameras, "points": n_points, "noise_px": noise,
            "seed": seed, "observations": int(seen.sum()), "longest_track": int(seen.sum(0).max()),
            "wall_s": round(wall, 2), "rms_px": report.get("reprojection_rms_px"),
            "error_pct": round(100 * similarity_error(result.points, X[result.ids]), 5),
            "converged": not any("converge" in w for w in report.get("warnings", [])),
            "target_s": 15, "machine": machine}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, nargs="+", default=[250])
    parser.add_argument("--points", type=int, default=3000)
    parser.add_argument("--noise", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for count in args.cameras:
        print(json.dumps(case(count, args.points, args.noise, args.seed)), flush=True)


if __name__ == "__main__":
    main()
