"""The colmap experiment at several photo counts, one JSON line each.

    python benchmarks/colmap.py [--counts 25 50 100 250] [--shape chair] [--seed 0]

Each line is one ``pipeline=colmap`` run (rendering, COLMAP through pycolmap,
scoring, COLMAP's tracks fed to mpe3d) as ``mpe3d run`` computes it: its
wall time, the photos registered, COLMAP's points, CD and EMD (x 100, against
2048 surface samples), and the tracks' counts and CD to COLMAP's own
triangulation per method. A last line gives the 3DMPE row (4 projections,
known correspondences, Table allmetrics' protocol) by the paper's SGD and by
refine, beside the paper's numbers (COLMAP 250 images: CD 23.1, EMD 19.7;
3DMPE 4 projections: CD 5.79, EMD 5.09).
Each photo line also says what machine it ran on (``benchmarks/machine.py``).
"""

from __future__ import annotations

import argparse
import json
import time

from machine import describe

from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.execute import run

PAPER = {"colmap_250": {"cd_x100": 23.1, "emd_x100": 19.7}, "3dmpe_4": {"cd_x100": 5.79, "emd_x100": 5.09}}
KEPT = ("registered_images", "colmap_points", "colmap_models", "cd_x100", "emd_x100", "render_s",
        "extract_s", "match_s", "map_s", "runtime_s", "reprojection_px", "focal_error", "tracks_ge2",
        "tracks_ge3", "tracks_triangulated", "tracks_bundle_cd_x100", "tracks_sgd_cd_x100",
        "tracks_refine_cd_x100", "tracks_bundle_surface_cd_x100", "tracks_bundle_s", "tracks_sgd_s",
        "tracks_refine_s", "tracks_bundle_unplaced", "tracks_bundle_median_x100",
        "tracks_bundle_farthest")


def _round(value):
    return round(value, 4) if isinstance(value, float) else value


def colmap_line(count: int, shape: str, seed: int) -> dict:
    config = make_config({"pipeline": "colmap", "images.count": count, "shape": shape,
                          "points": 2048, "seed": seed})
    machine = describe()
    start = time.perf_counter()
    result = run(config)
    line = {"benchmark": "colmap", "photos": count, "shape": shape, "seed": seed,
            "wall_s": round(time.perf_counter() - start, 2), "machine": machine}
    line.update({k: _round(result.metrics[k]) for k in KEPT if k in result.metrics})
    line["paper"] = PAPER["colmap_250"]
    return line


def projections_line(shape: str, seed: int) -> dict:
    line = {"benchmark": "colmap", "pipeline": "points", "views": 4, "shape": shape, "seed": seed}
    for solver in ("sgd", "refine"):
        for setting in ("fixed", "variable"):
            config = make_config({"shape": shape, "points": 2048, "views": 4, "seed": seed,
                                  "visibility.mode": "zbuffer", "visibility.n_rays": 400,
                                  "projections": setting, "solver": solver})
            result = run(config)
            line[f"{solver}_{setting}"] = {"cd_x100": _round(result.metrics["cd_x100"]),
                                           "emd_x100": _round(result.metrics["emd_x100"]),
                                           "runtime_s": _round(result.metrics["runtime_s"])}
    line["paper"] = PAPER["3dmpe_4"]
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[25, 50, 100, 250])
    parser.add_argument("--shape", default="chair")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for count in args.counts:
        print(json.dumps(colmap_line(count, args.shape, args.seed)), flush=True)
    print(json.dumps(projections_line(args.shape, args.seed)), flush=True)


if __name__ == "__main__":
    main()
