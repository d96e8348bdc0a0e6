"""From matched keypoints to a 3D cloud, as a user with a tracker would.

Photographs a bundled mesh's surface points with 8 pinhole cameras around it,
adds half a pixel of noise, swaps 2 % of the matches for wrong ones and hides
each point from a third of the cameras, writes the keypoints as the CSV that
`mpe3d reconstruct` reads, reconstructs them and scores the cloud against
the points it came from (which the reconstruction never saw).

    python examples/keypoints_to_cloud.py [--shape chair] [--out keypoints.csv]
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import trimesh

import mpe3d
from mpe3d.harness.scene.shapes import load_shape


def photograph(points: np.ndarray, cameras: int, rng: np.random.Generator) -> pd.DataFrame:
    """Keypoints (view, point, x, y) in pixels of 640 x 480 pinhole photos."""
    rows = []
    for k in range(cameras):
        angle = 2 * np.pi * k / cameras
        centre = 3.0 * np.array([np.cos(angle), 0.4, np.sin(angle)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(right, forward), forward])  # world -> camera
        camera = (points - centre) @ R.T
        xy = 800.0 * camera[:, :2] / camera[:, 2:] + [320.0, 240.0]
        xy += rng.normal(scale=0.5, size=xy.shape)
        seen = rng.random(len(points)) > 1 / 3
        wrong = seen & (rng.random(len(points)) < 0.02)
        xy[wrong] = xy[rng.permutation(np.flatnonzero(wrong))] + rng.normal(scale=30, size=(wrong.sum(), 2))
        rows += [(f"cam{k}", int(i), *xy[i]) for i in np.flatnonzero(seen)]
    return pd.DataFrame(rows, columns=["view", "point", "x", "y"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", default="chair", help="a bundled shape (mpe3d shapes lists them)")
    parser.add_argument("--points", type=int, default=300)
    parser.add_argument("--out", type=Path, help="where to keep the keypoints CSV (default: a temporary folder)")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    mesh = load_shape(args.shape)
    truth = trimesh.sample.sample_surface(mesh, args.points, seed=0)[0]
    truth = (truth - truth.mean(axis=0)) / np.ptp(truth, axis=0).max()
    with tempfile.TemporaryDirectory() as folder:
        path = args.out or Path(folder) / "keypoints.csv"
        photograph(truth, 8, rng).to_csv(path, index=False)
        result = mpe3d.reconstruct(path)  # bundle adjustment; the camera model is chosen from the data
    report = result.report
    # the cloud is in its own frame: align it to the truth (a similarity) before comparing
    ids = result.ids.astype(int)
    placed = ~np.isin(ids, result.unplaced.astype(int))
    matrix, aligned, _ = trimesh.registration.procrustes(result.points[placed], truth[ids[placed]],
                                                        reflection=True, scale=True)
    error = np.linalg.norm(aligned - truth[ids[placed]], axis=1)
    print(f"{report['points']} points from {report['views']} views, {report['camera']} camera: "
          f"reprojection RMS {report['reprojection_rms_px']:.2f} px, "
          f"{len(result.dropped)} wrong matches dropped, {len(result.unplaced)} unplaced")
    print(f"median distance to the true points: {np.median(error):.4f} (the object is 1 unit across)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
