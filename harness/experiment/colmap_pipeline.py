"""The ``colmap`` pipeline of a run: photos -> COLMAP -> its points, and its tracks -> mpe3d.

The paper's Table colmap (Section "Exploratory Integration with COLMAP"):
COLMAP reconstructs the mesh from rendered photos, its sparse points are
moved into the mesh's frame by the similarity that takes its camera centres
onto the true ones (the only use of ground truth before scoring), and scored
with CD and EMD against the surface samples, as every other table is.

Then the paper's own pipeline: COLMAP's feature tracks (its verified
matches joined into tracks, :func:`mpe3d.harness.experiment.colmap_sfm.database_tracks`),
not its points, are fed to mpe3d, by bundle adjustment (``bundle``) and by
the 3DMPE stress of their pixel distances (``sgd``, the paper's, and
``refine``, ours), each cloud scored against COLMAP's own triangulation of
the same tracks and against the surface (on those tracks).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from mpe3d import solvers
from mpe3d.errors import Unregistered
from mpe3d.harness.experiment import colmap_sfm
from mpe3d.harness.experiment.config import RunConfig
from mpe3d.harness.experiment.result import RunResult, short_number
from mpe3d.harness.scene import metrics, rendering, shapes
from mpe3d.harness.scene.observe import Scene
from mpe3d.harness.scene.visibility import SELF_HIT_TOLERANCE
from mpe3d.harness.userdata import photos
from mpe3d.options import OUTLIER_THRESHOLD
from mpe3d.solvers.sfm import colmap
from mpe3d.solvers.sfm.stages import AUTO_RATIO, shows_perspective
from mpe3d.solvers.sfm.support import median_radii

TRACK_METHODS = ("bundle", "sgd", "refine")  # what COLMAP's tracks are fed to, in this order
MIN_ALIGNED = 3  # registered photos (or shared tracks) a similarity needs


def seen_in_photos(mesh, points: np.ndarray, cameras: rendering.PhotoCameras) -> np.ndarray:
    """(K, N) visibility of ``points`` in the photos: in the frame, in front,
    and no surface between the point and the camera centre."""
    pixels, depth = cameras.project(points)
    inside = (depth > 0) & np.all((pixels >= 0) & (pixels < [cameras.width, cameras.height]), axis=2)
    for k, centre in enumerate(cameras.centres):
        rows = np.flatnonzero(inside[k])
        towards = centre - points[rows]
        towards /= np.linalg.norm(towards, axis=1, keepdims=True)
        origins = points[rows] + SELF_HIT_TOLERANCE * towards
        # the cameras stand outside the bounding sphere: any hit is between point and camera
        blocked = mesh.ray.intersects_any(origins, towards)
        inside[k, rows[blocked]] = False
    return inside


def _to_mesh_frame(sfm: colmap_sfm.SfmResult, cameras: rendering.PhotoCameras, names: list[str], rng):
    """The similarity from COLMAP's frame to the mesh's, fitted robustly on the
    camera centres of the registered photos (true against estimated)."""
    order = {name: k for k, name in enumerate(names)}
    registered = [n for n in names if n in sfm.registered]
    true = cameras.centres[[order[n] for n in registered]]
    estimated = np.array([sfm.centres[n] for n in registered])
    return metrics.robust_similarity(estimated, true, rng)


def _apply(transform, points: np.ndarray) -> np.ndarray:
    s, Q, t = transform
    return s * points @ Q.T + t


def _scores(cloud: np.ndarray, truth: np.ndarray, prefix: str = "") -> dict[str, float]:
    out = {**metrics.chamfer(cloud, truth), **metrics.earth_movers(cloud, truth)}
    return {f"{prefix}{k}": v for k, v in out.items()}


def _fed_to(method: str, views: list[dict], principal_point, pinhole: bool = False):
    """mpe3d's cloud of COLMAP's tracks (ids = track index) by ``method``: the
    solve of :func:`~mpe3d.harness.userdata.reconstruct.reconstruct` on views
    made here, without the checks that a user's files need.

    ``pinhole``: bundle adjustment found that a pinhole explains the tracks
    clearly better than weak perspective (:func:`model_misfit`). The stress's
    orthographic projections then misfit every row a little, and refine's
    rejection rounds would chase that misfit's tail round after round (each
    at its iteration cap) instead of wrong matches, which the pinhole's fit
    has already dealt with: they are turned off (``outlier_threshold=inf``)."""
    from mpe3d.harness.userdata.observations import observations_from
    from mpe3d.harness.userdata.reconstruct import Problem, solve_problem

    observations, ids = observations_from(views)
    names = [str(view.get("name", k)) for k, view in enumerate(views)]
    if method == "bundle":
        return solve_problem(Problem(observations, ids, "bundle", "l2", 0, objective="reprojection",
                             camera="perspective", principal_point=tuple(principal_point),
                             view_names=names))
    return solve_problem(Problem(observations, ids, method, "l2", 0, objective="stress", view_names=names,
                                 outlier_threshold=np.inf if pinhole else OUTLIER_THRESHOLD))


def model_misfit(bundle_report: dict) -> bool:
    """Whether bundle adjustment's pinhole explains the keypoints clearly better
    than the scaled (weak-perspective) camera: its RMS below AUTO_RATIO of the
    scaled fit's on the same observations (camera="auto"'s test, on the RMS
    both fits report rather than the median), or, where no scaled fit was
    needed, two views at a time already showing perspective."""
    by_camera = bundle_report.get("rms_px_by_camera", {})
    pinhole, scaled = by_camera.get("perspective"), by_camera.get("scaled")
    if pinhole is not None and scaled is not None:
        return pinhole < AUTO_RATIO * scaled
    noise, affine = (bundle_report.get(key) for key in ("keypoint_noise_px", "affine_misfit_px"))
    return pinhole is not None and None not in (noise, affine) and shows_perspective(noise, affine)


def _track_scores(tracks, sfm, to_mesh, truth, principal_point, rng) -> tuple[dict, list[str]]:
    """Track counts, and each method's cloud against COLMAP's triangulation of the same tracks."""
    per_track = tracks.views_per_track()
    out = {"tracks_ge2": int(np.sum(per_track >= 2)), "tracks_ge3": int(np.sum(per_track >= 3)),
           "tracks_conflicting": tracks.conflicting}
    notes: list[str] = []
    pairs = colmap_sfm.triangulated(tracks, sfm)
    out["tracks_triangulated"] = len(pairs)
    views = tracks.views()
    if len(pairs) < MIN_ALIGNED or len(views) < 2:
        return out, notes
    row = {int(i): r for r, i in enumerate(sfm.point_ids)}
    colmap_points = _apply(to_mesh, sfm.points)
    views = photos.tied_views(views)
    out["tracks_photos_tied"] = len(views)
    pinhole = False
    for method in TRACK_METHODS:
        start = time.perf_counter()
        try:
            result = _fed_to(method, views, principal_point, pinhole)
        except Unregistered as exc:  # the method's own outcome; any other error fails the run
            notes.append(f"tracks -> {method}: {exc}")
            continue
        out[f"tracks_{method}_s"] = time.perf_counter() - start
        if method == "bundle":
            pinhole = model_misfit(result.report)
            out["tracks_model_misfit"] = float(pinhole)
        placed = ~np.isin(result.ids, result.unplaced)
        out[f"tracks_{method}_unplaced"] = len(result.unplaced)
        # in median radii: bundle adjustment leaves unplaced what stands beyond
        # FAR_FACTOR of them, so a point at infinity would show here
        out[f"tracks_{method}_farthest"] = float(median_radii(result.points[placed]).max()) \
            if placed.any() else float("nan")
        shared = [(k, row[pairs[int(i)]]) for k, i in enumerate(result.ids)
                  if placed[k] and int(i) in pairs]
        if len(shared) < MIN_ALIGNED:
            continue
        ours, theirs = (np.array(c) for c in zip(*shared))
        # robustly: a few tracks placed far out in depth (two views a degree apart)
        # would bend a least-squares fit of the whole cloud
        fit = metrics.robust_similarity(result.points[ours], colmap_points[theirs], rng, mirror=True)
        mine = _apply(fit, result.points[ours])
        out[f"tracks_{method}_cd_x100"] = metrics.chamfer(mine, colmap_points[theirs])["cd_x100"]
        apart = np.linalg.norm(mine - colmap_points[theirs], axis=1)
        out[f"tracks_{method}_rms"] = float(np.sqrt(np.mean(apart ** 2)))
        out[f"tracks_{method}_median_x100"] = 100.0 * float(np.median(apart))
        # against the surface on the same tracks too: a track that COLMAP left out may
        # lie at any depth (two views a degree apart), which would swamp a mean
        out[f"tracks_{method}_surface_cd_x100"] = metrics.chamfer(mine, truth)["cd_x100"]
    return out, notes


def run(config: RunConfig, streams) -> RunResult:
    """Render, run COLMAP, score: COLMAP's cloud as the reconstruction (in the
    mesh frame), scored against the mesh's surface samples."""
    mesh = shapes.load_shape(config["shape"])
    truth = shapes.sample_points(mesh, config["points"], streams["sampling"])
    cameras = rendering.spiral_cameras(config["images.count"], size=config["images.size"])
    scene = Scene(mesh=mesh, points=truth, rotations=cameras.rotations,
                  visible=seen_in_photos(mesh, truth, cameras))
    scores: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="mpe3d-colmap-") as work:
        work = Path(work)
        start = time.perf_counter()
        images = rendering.render(mesh, cameras, seed=config["seed"])
        names = rendering.save_images(images, work / "images")
        scores["render_s"] = time.perf_counter() - start
        sfm = colmap_sfm.run_sfm(work / "images", names, work, focal=cameras.focal,
                             principal_point=cameras.principal_point,
                             matching=config["images.matching"], seed=config["seed"])
        tracks = colmap_sfm.database_tracks(sfm.database)
    scores.update(sfm.seconds)
    colmap_s = sum(sfm.seconds.values())
    scores.update(runtime_s=colmap_s, iterations=0, images=len(names),
                  registered_images=len(sfm.registered),
                  registered_share=len(sfm.registered) / len(names), colmap_models=sfm.models,
                  colmap_points=len(sfm.points), points_kept=len(truth))
    facts = {"colmap_version": colmap_sfm.colmap_version(),
             "matching": colmap.matching_for(len(names), config["images.matching"]), "warnings": []}
    cloud = np.zeros((0, 3))
    if len(sfm.registered) >= MIN_ALIGNED and len(sfm.points):
        to_mesh = _to_mesh_frame(sfm, cameras, names, streams["metrics"])
        cloud = _apply(to_mesh, sfm.points)
        scores.update(_scores(cloud, truth))
        scores["reprojection_px"] = sfm.reprojection_px
        scores["focal_error"] = abs(sfm.focal / cameras.focal - 1.0)
        track_scores, notes = _track_scores(tracks, sfm, to_mesh, truth, cameras.principal_point,
                                            streams["metrics"])
        scores.update(track_scores)
        facts["warnings"] += notes
    else:
        per_track = tracks.views_per_track()
        scores.update(tracks_ge2=int(np.sum(per_track >= 2)), tracks_ge3=int(np.sum(per_track >= 3)))
        facts["warnings"].append(f"COLMAP registered {len(sfm.registered)} of {len(names)} photos: "
                                 "no model to score")
    termination = (f"COLMAP registered {len(sfm.registered)} of {len(names)} photos in "
                   f"{sfm.models} model(s), {len(sfm.points)} points")
    recon = solvers.Reconstruction(points=cloud, projections=cameras.rotations[:, :2],
                                   stress=float("nan"), stress_history=np.zeros(0), iterations=0,
                                   termination=termination, runtime_s=colmap_s)
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=cloud, facts=facts)


def method_name(config) -> str:
    """The photos' pipeline: COLMAP reconstructs, no solver of ours."""
    return "COLMAP"


def title(result: RunResult) -> str:
    config = result.config
    return (f"{config['shape']}  COLMAP, {config['images.count']} photos  "
            f"CD x100={result.metrics['cd_x100']:.3g}")


def describe(summary: dict[str, Any]) -> list[str]:
    cfg, images = summary["config"], summary["config"]["images"]
    lines = [f"shape {cfg['shape']}, {images['count']} photos of {images['size']} px, COLMAP "
             f"against N={cfg['points']} surface samples, seed {cfg['seed']}",
             summary["termination"]]
    if "cd_x100" in summary:
        lines.append(f"cd_x100={short_number(summary['cd_x100'])}  emd_x100={short_number(summary['emd_x100'])}  "
                     f"reprojection {summary['reprojection_px']:.3f} px")
    tracks = [f"{k}={short_number(summary[k])}" for k in summary if k.startswith("tracks_")
              and k.endswith(("ge2", "ge3", "triangulated", "cd_x100"))]
    lines.append("COLMAP's tracks: " + "  ".join(tracks))
    lines.append(f"render {summary['render_s']:.1f} s, COLMAP {summary['runtime_s']:.1f} s, "
                 f"total {summary['wall_s']:.1f} s")
    return lines
