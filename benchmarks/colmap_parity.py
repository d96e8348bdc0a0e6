"""Ours against COLMAP's mappers on identical raw matches: a thin front of ``sweeps/photos.yaml``.

    python benchmarks/colmap_parity.py [--shapes airplane chair lamp] [--sizes 10 25 100]
                                       [--seeds 0 1 2] [--photos-root DIR] [--jobs 2]
                                       [--solver NAME --plugin FILE]

There is one way to run the comparison: the ``photos`` sweep (``mpe3d sweep
sweeps/photos.yaml``), which renders the bundled shapes along a spiral
(exact reference poses), reads every data set under ``--photos-root``,
computes each set's features and raw matches once, gives the same tracks to
mpe3d's bundle adjustment and COLMAP's incremental and global mappers, and
scores each by COLMAP's relative-pose AUC. This script runs that sweep with
the shapes, sizes and seeds asked for (tracked in ``$MLFLOW_TRACKING_URI``,
else ``sqlite:///mlflow.db``: a rerun computes nothing again), then prints one
JSON line per run from the tracked records: data set, method, AUC@1/3/5/10,
registered photos, centre error, RMS, points and the time split.
``mpe3d report --sweep sweeps/photos.yaml ...`` renders the same runs as a
table, a figure and the findings.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from machine import describe

SWEEP = Path(__file__).resolve().parents[1] / "sweeps" / "photos.yaml"
COLUMNS = ("photos.set", "shape", "images.count", "seed", "photos.solver", "status", "pose_auc1", "pose_auc3",
           "pose_auc5", "pose_auc10", "registered", "photos", "centre_error", "rms_px", "points_placed",
           "extract_s", "match_s", "solve_s", "features_cached")


def overrides(args) -> list[str]:
    out = [f"grid.shape=[{', '.join(args.shapes)}]", f"grid.images.count=[{', '.join(map(str, args.sizes))}]",
           f"seeds=[{', '.join(map(str, args.seeds))}]"]
    return out + ([f"photos.root={args.photos_root}"] if args.photos_root else [])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["airplane", "chair", "lamp"])
    parser.add_argument("--sizes", nargs="+", type=int, default=[10, 25, 100])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--photos-root", type=Path, help="a folder of photo data sets (images/ and a reference)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--solver", action="append", default=[], help="an SfM plug-in's name (with --plugin)")
    parser.add_argument("--plugin", action="append", default=[])
    args = parser.parse_args(argv)
    print(json.dumps({"machine": describe()}), flush=True)
    given = overrides(args)
    extra = [*(f"--solver={n}" for n in args.solver), *(f"--plugin={p}" for p in args.plugin)]
    done = subprocess.run([str(Path(sys.executable).parent / "mpe3d"), "sweep", str(SWEEP), *given, "--jobs",
                           str(args.jobs), "--quiet", *extra])
    if done.returncode not in (0, 1):  # 1: some runs failed, and are listed as such below
        return done.returncode
    from mpe3d import plugins
    from mpe3d.harness.experiment.sweep import load_sweep
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports.load import runs

    plugins.load_files(args.plugin)
    sweep = load_sweep(SWEEP, overrides=given)
    if args.solver:
        from mpe3d.harness.experiment.axes import add_solvers

        sweep = add_solvers(sweep, args.solver)
    frame = runs(Tracker(), sweep.name, hashes=[c.hash() for c in sweep.runs])
    for row in frame.to_dict("records"):
        print(json.dumps({key: row.get(key) for key in COLUMNS}, default=str), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
