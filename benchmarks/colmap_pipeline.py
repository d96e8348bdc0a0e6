"""COLMAP's whole pipeline on a folder of photos, as a user runs it through pycolmap.

    python benchmarks/colmap_pipeline.py IMAGES OUT [--threads 2] [--mapper incremental|global]

SIFT features at COLMAP's defaults (one shared camera, SIMPLE_RADIAL: what
``mpe3d reconstruct`` makes of the camera per photo that COLMAP's extractor
writes for one camera's photos), matched as mpe3d matches them
(exhaustively up to 50 photos, each with its 10 neighbours on each side of
the path beyond; geometric verification on, COLMAP's default), then the
incremental mapper (or the global one) at its defaults. The models go to
``OUT/sparse/N``; one JSON line gives each step's seconds, the photos
registered and the points of the largest model. This is the process
``benchmarks/photos_vs_colmap.py`` times against ``mpe3d reconstruct``: it
calls pycolmap itself, not mpe3d's adapter (``mpe3d.solvers.sfm.colmap``),
so that COLMAP's process pays no import of mpe3d.
"""

from __future__ import annotations

import time

START = time.perf_counter()

import argparse  # noqa: E402  (the clock starts before the imports, as a process's does)
import json  # noqa: E402
import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import pycolmap  # noqa: E402

EXHAUSTIVE_UP_TO = 50  # mpe3d.solvers.sfm.colmap.EXHAUSTIVE_UP_TO
SEQUENTIAL_OVERLAP = 10


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("images", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--threads", type=int, default=-1)
    parser.add_argument("--mapper", choices=("incremental", "global"), default="incremental")
    args = parser.parse_args()
    seconds = {"import_s": time.perf_counter() - START}
    shutil.rmtree(args.out, ignore_errors=True)
    (args.out / "sparse").mkdir(parents=True)
    database = args.out / "database.db"
    count = sum(1 for p in args.images.iterdir() if p.is_file())

    start = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = args.threads
    pycolmap.extract_features(database, args.images, camera_mode=pycolmap.CameraMode.SINGLE,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["extract_s"] = time.perf_counter() - start

    start = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = args.threads
    if count <= EXHAUSTIVE_UP_TO:
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.loop_detection = False
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    seconds["match_s"] = time.perf_counter() - start

    start = time.perf_counter()
    if args.mapper == "incremental":
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = args.threads
        models = pycolmap.incremental_mapping(database, args.images, args.out / "sparse", options=options)
    else:
        options = pycolmap.GlobalPipelineOptions()
        options.num_threads = args.threads
        models = pycolmap.global_mapping(database, args.images, args.out / "sparse", options=options)
    seconds["map_s"] = time.perf_counter() - start
    best = max(models.values(), key=lambda m: m.num_reg_images()) if models else None
    print(json.dumps({**{k: round(v, 3) for k, v in seconds.items()},
                      "registered": best.num_reg_images() if best else 0,
                      "points": best.num_points3D() if best else 0,
                      "models": len(models), "total_s": round(time.perf_counter() - START, 3)}))


if __name__ == "__main__":
    main()
