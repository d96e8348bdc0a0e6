"""``mpe3d reconstruct``: your own keypoints or distance matrices in, a 3D
cloud (and a report, a COLMAP model or a Bundler/BAL file) out."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from mpe3d.errors import MpeError
from mpe3d.options import (
    CAMERAS,
    COLMAP_SOLVERS,
    DEFAULT_MATCHES,
    MATCHES,
    OBJECTIVES,
    OUTLIER_THRESHOLD,
    REPROJECTION_LOSSES,
    REPROJECTION_SOLVERS,
    STARTS,
)


def _pair(text: str):
    """``X,Y`` as two numbers, for --missing and --principal-point."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y (two numbers), got {text!r}") from None
    return x, y


def add_parser(sub) -> None:
    rec = sub.add_parser("reconstruct", help="rebuild a 3D cloud from your photos, keypoints or "
                         "distance matrices", description="Read photos (SIFT features and matches by "
                         "pycolmap), matched 2D keypoints (CSV view,point,x,y; NPZ; JSON; a folder of "
                         ".npz per view; COLMAP, Bundler, BAL, VGG files) or per-view distance matrices, "
                         "check them, and write the 3D cloud with each point's id.")
    rec.add_argument("input", metavar="INPUT", help="a folder of photos (any cameras), a COLMAP "
                     "database (database.db) or model folder, a .csv, .npz or .json file, a folder "
                     "of .npz, a Bundler .out or BAL problem file, or a VGG nview-corners table (its "
                     ".corners files beside it)")
    rec.add_argument("--out", required=True, metavar="CLOUD",
                     help="output: .ply, .csv or .npy (the cloud, with ids); a folder (a COLMAP "
                     "model); or .out or .bal (Bundler or BAL: pinhole cameras f, k1, k2, the "
                     "points and the kept keypoints, centred on the principal point)")
    rec.add_argument("--projections", metavar="FILE",
                     help="known cameras (.npy or .json, K matrices: 2x3 or 3x3 orthographic, "
                     "or 3x4 pinhole): the fixed setting")
    rec.add_argument("--objective", choices=OBJECTIVES.names,
                     help="reprojection (bundle adjustment; the default for keypoints) or "
                     "stress (paper Eq. 1; the default and only choice for distance matrices)")
    rec.add_argument("--camera", default="auto",
                     choices=CAMERAS.names,
                     help="the camera model for reprojection (default auto: the pinhole camera "
                     "where two views show perspective or it fits clearly better than weak "
                     "perspective, with its lens where an information criterion says the keypoints "
                     "show one; radial: the pinhole with radial distortion k1, k2, Bundler's and "
                     "BAL's camera)")
    rec.add_argument("--start", choices=STARTS.names,
                     help="where bundle adjustment starts: the input's cameras and points (a "
                     "Bundler or BAL file; the default when it has them) or mpe3d's own start")
    rec.add_argument("--principal-point", type=_pair, metavar="X,Y",
                     help="the pinhole camera's principal point in pixels, usually the image "
                     "centre (default: the centre of the keypoints)")
    rec.add_argument("--missing", type=_pair, metavar="X,Y",
                     help="drop observations at exactly X,Y (e.g. -1,-1: a tracker's 'not seen')")
    rec.add_argument("--outlier-threshold", type=float, default=OUTLIER_THRESHOLD, metavar="SIGMAS",
                     help="reprojection: drop observations beyond this many robust sigmas as "
                     f"wrong matches (default {OUTLIER_THRESHOLD:g}; inf keeps all, and turns refine's "
                     "rejection rounds off for the stress)")
    rec.add_argument("--solver", metavar="NAME",
                     help=f"who minimises the objective. Reprojection: {' or '.join(REPROJECTION_SOLVERS)} "
                     "(default bundle: mpe3d's bundle adjustment; colmap: COLMAP's geometric "
                     "verification and incremental mapper on the same tracks; colmap_global: the same "
                     "verification and COLMAP's global mapper, GLOMAP's). Stress: refine "
                     "(default) or any other of `mpe3d solvers`, a plug-in's (--plugin) included")
    rec.add_argument("--matches", default=DEFAULT_MATCHES, choices=MATCHES.names,
                     help=f"photos and COLMAP databases: track the matcher's raw matches (default "
                     f"{DEFAULT_MATCHES}; wrong ones are found by the solve) or only the geometrically "
                     "verified ones")
    rec.add_argument("--scratch", metavar="DIR",
                     help="photos and --solver colmap or colmap_global: the folder COLMAP's database is written to "
                     "(default: the system's temporary folder); its free space is checked first "
                     "against an estimate of the features and matches (docs/guide/reconstruct.md); exit 3 "
                     "when it falls short")
    rec.add_argument("--loss", choices=REPROJECTION_LOSSES.names,
                     help="l2, or a robust loss: huber, soft_l1 (cauchy: reprojection only); default "
                     "soft_l1 for bundle adjustment of photos' and COLMAP databases' tracks, l2 otherwise")
    rec.add_argument("--report", metavar="FILE.json", help="write per-view residuals (pixels "
                     "for reprojection), cameras, dropped and unplaced ids and runtime as JSON")
    rec.add_argument("--reference", metavar="REF",
                     help="photos: score the cameras against reference poses, a COLMAP model (a sparse/0 "
                     "or sparse folder, text or binary, or the folder holding it) or a Bundler .out "
                     "(named by the list.txt beside it, else the photos in name order): relative-pose "
                     "AUC@1/3/5/10 as COLMAP's benchmark defines it, photos registered, camera-centre "
                     "error (docs/guide/reconstruct.md)")
    rec.add_argument("--seed", type=int, default=0, help="random state (default 0)")
    rec.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                     help="load a plug-in file (a stress solver for --solver) first; repeatable")
    rec.set_defaults(func=cmd_reconstruct)


def cmd_reconstruct(args) -> int:
    from mpe3d.harness.userdata import bundler
    from mpe3d.harness.userdata.formats import OUTPUT_FORMATS, check_ids_fit, check_output, write_result
    from mpe3d.harness.userdata.reconstruct import prepare, solve_problem

    if args.seed < 0:
        raise MpeError(f"--seed: expected an integer >= 0, got {args.seed}")
    model = _model_out(args.out)  # every output path before any work, not after it
    out = model / "points3D.ply" if model else \
        check_output(args.out, formats=OUTPUT_FORMATS + bundler.BUNDLE_OUTPUTS)
    solution = out.suffix.lower() in bundler.BUNDLE_OUTPUTS
    report = check_output(args.report, "--report", (".json",)) if args.report else None
    if report is not None and report.resolve() == out.resolve():
        raise MpeError(f"--report {report}: the same file as --out")
    reference = _reference(args.reference, args.input) if args.reference else None  # before any work
    with _working(f"reading {args.input}" + (" (SIFT features and matches by pycolmap)"
                                               if Path(args.input).is_dir() else "")):
        problem = prepare(args.input, projections=args.projections, solver=args.solver,
                          loss=args.loss, random_state=args.seed, objective=args.objective,
                          camera=args.camera, missing=args.missing,
                          outlier_threshold=args.outlier_threshold,
                          principal_point=args.principal_point, start=args.start, matches=args.matches,
                          scratch=args.scratch)
    check_ids_fit(out, problem.ids)
    if solution:
        bundler.check_solution_out(out, problem)
    with _working(f"solving {problem.observations.n_views} views by {problem.solver}"):
        result = solve_problem(problem)
    extra = {"input": str(args.input), "output": str(model or out)}
    scores = _scored(reference, result, args.seed) if reference else None
    if scores:
        from mpe3d.harness.userdata.references import unscored

        extra["reference"] = scores
        result.warnings.extend(filter(None, [unscored(result)]))
    if model:
        from mpe3d.harness.userdata.colmap_model import write_model_folder

        result.warnings.extend(write_model_folder(model, problem, result))
    writer = bundler.solution_writer(out, problem, result) if solution else None
    write_result(out, result, report, extra, writer)
    print(_summary(result.report) + (_pose_summary(scores) if scores else ""))
    for message in [*result.warnings, *(reference.notes if reference else ())]:
        print(f"mpe3d: warning: {message}", file=sys.stderr)
    print(f"wrote {model or out}" + (f" and {report}" if report else ""))
    return 0


def _working(text: str):
    """A spinner with the elapsed time on a terminal (photos take minutes to
    extract and match), nothing when stderr is a file or a pipe."""
    from contextlib import nullcontext

    if not sys.stderr.isatty():
        return nullcontext()
    from rich.console import Console

    return Console(stderr=True).status(f"{text} ...")


def _model_out(text: str) -> Path | None:
    """The folder of a COLMAP model when ``--out`` names one (no file suffix),
    checked as :func:`check_output` checks a file."""
    from mpe3d.harness.userdata.colmap_model import check_model_out

    path = Path(text)
    if text.endswith(("/", os.sep)) or not path.suffix:
        return check_model_out(path)
    return None


def _summary(summary: dict) -> str:
    where = f"{summary['points']} points from {summary['views']} views ({summary['setting']} "
    if summary["objective"] == "stress":
        worst = max(summary["rms_residual_per_view"])
        return (where + f"projections, {summary['solver']}): stress {summary['stress']:.3g}, "
                f"worst view RMS residual {worst:.3g}, {summary['unplaced']['count']} unplaced, "
                f"{summary['runtime_s']:.2f} s")
    worst = max(v for v in summary["rms_px_per_view"] if v is not None)
    method = "bundle adjustment" if summary["solver"] == "bundle" \
        else f"COLMAP's {COLMAP_SOLVERS[summary['solver']]} mapper"
    return (where + f"cameras, {summary['camera']} camera, {method}): reprojection RMS "
            f"{summary['reprojection_rms_px']:.3g} px (worst view {worst:.3g} px), "
            f"{summary['dropped']['count']} wrong matches dropped, "
            f"{summary['unplaced']['count']} unplaced, {summary['runtime_s']:.2f} s")


def _reference(text: str, photos: str):
    """The reference poses, read (and refused in one line) before any photo is
    read; a Bundler file without its list.txt names its cameras by the photos."""
    from mpe3d.harness.userdata.photo_folder import list_photos
    from mpe3d.harness.userdata.references import read_reference

    names = list_photos(Path(photos)) if Path(photos).is_dir() else None
    try:
        return read_reference(text, names)
    except MpeError as exc:
        raise type(exc)(f"--reference {exc.message}", exc.key, exc.hint) from None


def _scored(reference, result, seed: int) -> dict:
    """The report's ``reference`` entry: :func:`score_poses` and what was read (NaN written as null)."""
    from mpe3d.harness.scene.metrics import score_poses
    from mpe3d.harness.userdata.references import poses_of

    scores = score_poses(reference, poses_of(result), random_state=seed)
    return {k: None if isinstance(v, float) and v != v else v for k, v in scores.items()} \
        | {"source": reference.source}


def _pose_summary(scores: dict) -> str:
    """``; pose AUC@3 71.2 (AUC@1/5/10 40.1/80.3/89.9), 11/11 photos registered``, for the summary line."""
    others = "/".join(f"{scores[f'pose_auc{t}']:.1f}" for t in (1, 5, 10))
    return (f"; pose AUC@3 {scores['pose_auc3']:.1f} (AUC@1/5/10 {others}), "
            f"{scores['registered']}/{scores['photos']} photos registered")
