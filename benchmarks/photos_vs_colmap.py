"""Photos to cameras end to end, ours against COLMAP's whole pipeline, scored by pose AUC.

    python benchmarks/photos_vs_colmap.py [--sizes 10 25 100 250] [--shape chair] [--seed 0]
                                          [--real DIR ...] [--threads 2] [--mapper incremental]

Each photo set is given to two whole processes started as a user starts
them, on the same cores (``--threads``: the process's CPU affinity, and
COLMAP's thread count): ``mpe3d reconstruct IMAGES --out MODEL/`` (every
default) and ``benchmarks/colmap_pipeline.py`` (pycolmap's SIFT, matching,
geometric verification and mapper at COLMAP's defaults, one shared camera,
the same pairs matched). Each line: both wall times and their ratio, the
photos each registers, and the pose AUC at 0.5, 1, 3, 5 and 10 degrees of
each model against the reference poses, COLMAP's own benchmark's
relative-pose metric (:func:`mpe3d.harness.scene.metrics.pose_auc`).

Rendered sets: the bundled ``--shape`` along the parity benchmark's spiral
(``rendering.photo_spiral``: 400-px photos 15-18 degrees apart), ``--sizes``
photos, exact reference poses; kept under ``--work`` between runs.
``--real DIR``: a folder holding ``images/`` and its reference, a COLMAP
model (``sparse/0`` or ``sparse``), a Bundler ``.out`` (its ``list.txt``
beside it, else the photos in name order) or Strecha's ``*.camera`` files
(``gt_dense_cameras/``). A real set fetched for this goes to a scratch
folder, never into the repository.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine import describe

from mpe3d.harness.scene.metrics import POSE_AUC_THRESHOLDS, pose_auc, relative_pose_errors

HERE = Path(__file__).resolve().parent


def rendered(shape: str, count: int, seed: int, work: Path, k1: float = 0.0,
             fill: float | None = None) -> tuple[Path, dict]:
    """The rendered set's images folder and its exact poses, made once:
    through a lens of radial distortion ``k1`` (COLMAP's RADIAL camera), the
    bounding sphere filling ``fill`` of the width (None: the spiral's 0.85)."""
    from mpe3d.harness.scene import rendering, shapes

    folder = work / (f"{shape}-{count}-s{seed}" + (f"-k{k1:g}" if k1 else "") + (f"-fill{fill:g}" if fill else ""))
    cams = rendering.photo_spiral(count, 400, seed, fill=fill or 0.85)
    cams = rendering.PhotoCameras(cams.rotations, cams.translations, cams.focal, cams.width, cams.height, (k1, 0.0))
    names = [f"image_{k:04d}.png" for k in range(count)]
    if not (folder / "done").exists():
        rendering.save_images(rendering.render(shapes.load_shape(shape), cams, seed=seed), folder / "images")
        (folder / "done").touch()
    return folder / "images", {n: (R, t) for n, R, t in zip(names, cams.rotations, cams.translations)}


def reference(folder: Path) -> dict:
    """``{photo name: (R, t)}`` of a real set's reference (see the module doc):
    a COLMAP model or Bundler file as ``mpe3d`` reads one, else Strecha's
    ``*.camera`` files."""
    from mpe3d.harness.userdata.photo_folder import list_photos
    from mpe3d.harness.userdata.references import read_reference, reference_in

    found = reference_in(folder)
    if found is not None:
        return read_reference(found, list_photos(folder / "images")).poses
    cameras = sorted(folder.glob("**/*.camera"))
    if cameras:
        return {p.name[:-len(".camera")]: _strecha(p) for p in cameras}
    sys.exit(f"{folder}: no reference (sparse/0, sparse, a Bundler .out or Strecha .camera files)")


def _strecha(path: Path):
    """Strecha's camera file: K, distortion, R (camera to world), C, size; P = K [R^T | -R^T C]."""
    rows = [list(map(float, line.split())) for line in path.read_text().splitlines() if line.strip()]
    R, C = np.array(rows[4:7]), np.array(rows[7])
    return R.T, -R.T @ C


def model_poses(model: Path) -> dict:
    from mpe3d.solvers.sfm import colmap

    return {name: (image.rotation, image.translation) for name, image in colmap.read_model(model).images.items()}


def largest_model(sparse: Path) -> dict:
    models = [model_poses(m) for m in sorted(sparse.iterdir()) if m.is_dir()]
    return max(models, key=len) if models else {}


def _affinity(threads: int):
    cpus = sorted(os.sched_getaffinity(0))[:threads]
    return lambda: os.sched_setaffinity(0, cpus)


def timed(command: list[str], threads: int) -> tuple[float, subprocess.CompletedProcess]:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env, preexec_fn=_affinity(threads))
    return time.perf_counter() - start, done


def scores(poses: dict, truth: dict) -> dict:
    aucs = pose_auc(relative_pose_errors(truth, poses), (0.5, *POSE_AUC_THRESHOLDS))
    return {"registered": sum(n in poses for n in truth),
            **{key.replace("pose_", ""): round(a, 2) for key, a in aucs.items()}}


def case(name: str, images: Path, truth: dict, work: Path, threads: int, mapper: str) -> dict:
    out = work / "runs" / name
    out.mkdir(parents=True, exist_ok=True)
    mpe3d = str(Path(sys.executable).parent / "mpe3d")
    ours_s, ours = timed([mpe3d, "reconstruct", str(images), "--out", str(out / "ours") + "/",
                          "--report", str(out / "ours.json")], threads)
    theirs_s, theirs = timed([sys.executable, str(HERE / "colmap_pipeline.py"), str(images), str(out / "colmap"),
                              "--threads", str(threads), "--mapper", mapper], threads)
    line = {"benchmark": "photos_vs_colmap", "set": name, "photos": len(truth), "threads": threads,
            "ours_s": round(ours_s, 2), "colmap_s": round(theirs_s, 2), "ratio": round(ours_s / theirs_s, 3)}
    if ours.returncode == 0:
        report = json.loads((out / "ours.json").read_text())
        line["ours"] = {**scores(model_poses(out / "ours"), truth), "camera": report["camera"],
                        "solve_s": round(report["runtime_s"], 2), "rms_px": round(report["reprojection_rms_px"], 3)}
    else:
        line["ours_error"] = (ours.stderr.strip().splitlines() or ["?"])[-1]
    if theirs.returncode == 0:
        steps = json.loads(theirs.stdout.strip().splitlines()[-1])
        line["colmap"] = {**scores(largest_model(out / "colmap" / "sparse"), truth),
                          **{k: steps[k] for k in ("extract_s", "match_s", "map_s")}}
    else:
        line["colmap_error"] = (theirs.stderr.strip().splitlines() or ["?"])[-1]
    return line


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", type=int, default=[10, 25, 100, 250])
    parser.add_argument("--shape", default="chair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--lens", type=float, default=0.0, metavar="K1",
                        help="render through a lens of radial distortion K1 (COLMAP's RADIAL camera)")
    parser.add_argument("--fill", type=float, help="the bounding sphere's share of the photo's width "
                        "(default 0.85; over 1, the object fills the frame)")
    parser.add_argument("--real", nargs="*", type=Path, default=[])
    parser.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--mapper", choices=("incremental", "global"), default="incremental")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "mpe3d-photos")
    args = parser.parse_args(argv)
    print(json.dumps({"machine": describe()}), flush=True)
    for count in args.sizes:
        images, truth = rendered(args.shape, count, args.seed, args.work, args.lens, args.fill)
        print(json.dumps(case(images.parent.name, images, truth, args.work, args.threads, args.mapper)),
              flush=True)
    for folder in args.real:
        print(json.dumps(case(folder.name, folder / "images", reference(folder), args.work, args.threads,
                              args.mapper)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
