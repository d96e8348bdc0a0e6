"""Reconstruct your own data: matched 2D keypoints (or distance matrices) -> a 3D cloud.

:func:`reconstruct` joins three parts kept apart: the file formats
(:mod:`mpe3d.harness.userdata.formats`), the checks of what they hold (here, every
error one line naming the file, view and row), and the solve:

* views given as 2D coordinates (keypoints, in pixels) pose bundle
  adjustment, the reprojection error over the points and each view's camera
  (``objective="reprojection"``, :mod:`mpe3d.solvers.sfm.bundle`), with a camera
  model (``camera``: orthographic, scaled, perspective, or auto), wrong
  matches found and dropped;
* distance matrices pose the 3DMPE stress (paper Eq. 1, ``objective="stress"``,
  solved by ``solver``), which coordinates can also ask for.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mpe3d import solvers
from mpe3d.errors import MpeError
from mpe3d.harness.userdata.formats import is_photo_folder, read_projections, read_views
from mpe3d.harness.userdata.observations import drop_missing, observations_from
from mpe3d.harness.userdata.results import Result, reprojection_result, stress_result
from mpe3d.options import (
    CAMERAS,
    COLMAP_SOLVERS,
    DEFAULT_MATCHES,
    OBJECTIVES,
    OUTLIER_THRESHOLDS,
    REPROJECTION_LOSSES,
    REPROJECTION_SOLVERS,
    STARTS,
    STRESS_LOSSES,
)
from mpe3d.solvers import Observations
from mpe3d.solvers.degenerate import check_geometry, collect_notes
from mpe3d.solvers.sfm import bundle, camera_groups, colmap_mapper
from mpe3d.solvers.sfm.cameras import radial_cameras

# -- solving -------------------------------------------------------------------

@dataclass
class Problem:
    """User input, read and checked: what the solve needs, nothing computed yet."""

    observations: Observations
    ids: np.ndarray
    solver: str
    loss: str
    random_state: Any
    objective: str = "stress"
    camera: str = "auto"
    cameras: np.ndarray | None = None  # known: (K, 2, 3) rows or (K, 3, 4) pinhole matrices
    outlier_threshold: float = bundle.OUTLIER_THRESHOLD
    principal_point: tuple | None = None
    view_names: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    start: tuple | None = None  # (X, Cameras) from the file (Bundler, BAL), or None: ours
    image_size: tuple | None = None  # (width, height) of photos, when known
    focal: float | None = None  # a plausible EXIF focal length in pixels, when known
    view_cameras: np.ndarray | None = None  # (K,) each photo's camera, photos of several; None: one
    image_sizes: np.ndarray | None = None  # (K, 2) each photo's (width, height), with view_cameras
    # (K, 2) each photo's principal point less the shared one, with view_cameras: its
    # keypoints were moved by it for the solve, and its reported camera gets it back
    view_offsets: np.ndarray | None = None
    scratch: Path | None = None  # where COLMAP's databases go; None: the system's temporary folder


def _check_random_state(random_state) -> None:
    if isinstance(random_state, np.random.Generator):
        return
    if isinstance(random_state, bool) or not isinstance(random_state, (int, np.integer)) \
            or random_state < 0:
        raise MpeError(f"random_state: expected an integer >= 0 or a numpy Generator, "
                       f"got {random_state!r}")


def _check_pair(value, name):
    if value is not None and (np.shape(value) != (2,) or not np.all(np.isfinite(value))):
        raise MpeError(f"{name}: expected two finite numbers x, y, got {value!r}")


def _check_choices(solver, loss, objective, camera, outlier_threshold, missing):
    if solver is not None and solver not in REPROJECTION_SOLVERS:
        solvers.get_solver(solver)  # any registered stress solver, a plug-in's too
    if objective is not None:
        OBJECTIVES.check("objective", objective)
    CAMERAS.check("camera", camera)
    if loss is not None:
        REPROJECTION_LOSSES.check("loss", loss)
    if isinstance(outlier_threshold, bool) or not isinstance(outlier_threshold, (int, float)):
        raise MpeError(f"outlier_threshold: expected a number, got {outlier_threshold!r}")
    OUTLIER_THRESHOLDS.check("outlier_threshold", outlier_threshold, "(inf keeps every observation)")
    _check_pair(missing, "missing")


def prepare(views: Sequence[dict] | str | Path, projections=None, solver: str | None = None,
            loss: str | None = None, random_state=0, objective: str | None = None,
            camera: str = "auto", missing=None,
            outlier_threshold: float = bundle.OUTLIER_THRESHOLD, principal_point=None,
            start: str | None = None, matches: str = DEFAULT_MATCHES, scratch=None) -> Problem:
    """Read and check every input of :func:`reconstruct` without solving anything."""
    _check_choices(solver, loss, objective, camera, outlier_threshold, missing)
    if start is not None:  # None: the file's when it has one
        STARTS.check("start", start)
    _check_pair(principal_point, "principal_point")
    _check_random_state(random_state)
    source = str(views) if isinstance(views, (str, Path)) else "views"
    if isinstance(views, (str, Path)):
        if is_photo_folder(views) and solver in (None, "bundle") and objective != "stress":
            _warm_during_extraction()
        seed = random_state if not isinstance(random_state, np.random.Generator) else 0
        views = read_views(views, matches, seed=int(seed), scratch=scratch)
    projections_source = "projections"
    if isinstance(projections, (str, Path)):
        projections_source, projections = str(projections), read_projections(projections)
    elif projections is not None:
        projections = np.asarray(projections, dtype=float)
        projections = projections if projections.shape[1:] == (3, 4) else projections[:, :2]
    views, notes = drop_missing(views, missing, source)
    notes = list(views[0].get("notes", [])) + notes if views else notes  # photos left out
    centres = [view.get("principal_point") for view in views]
    if principal_point is None and centres and all(c is not None for c in centres):
        principal_point = tuple(float(v) for v in centres[0])  # a COLMAP model's cameras
    coordinates = all("xy" in view for view in views)
    if objective is None:
        # keypoints pose the reprojection error, unless a stress solver is named
        objective = "reprojection" if solver in REPROJECTION_SOLVERS or (coordinates and solver is None) \
            else "stress"
    solver = _solver_for(objective, solver)
    loss = _loss_for(views, objective, solver) if loss is None else loss
    if objective == "reprojection" and not coordinates:
        raise MpeError(f"{source}: objective='reprojection' needs 2D coordinates (xy) in every "
                       "view; distance matrices allow objective='stress' only")
    if objective == "stress" and loss != "l2" and solver != "refine":
        raise MpeError(f"loss='{loss}' needs solver='refine' (got solver='{solver}')")
    if objective == "stress" and loss not in STRESS_LOSSES:
        raise MpeError(f"loss='{loss}' is for objective='reprojection'; the stress takes "
                       f"{', '.join(STRESS_LOSSES)}")
    pinhole = projections is not None and projections.shape[1:] == (3, 4)
    if pinhole and objective == "stress":
        raise MpeError(f"{projections_source}: 3x4 pinhole cameras need objective='reprojection'; "
                       "the stress takes orthographic projections (2x3 or 3x3)")
    obs, ids = observations_from(views, None if pinhole else projections, source,
                                 projections_source)
    if pinhole and len(projections) != obs.n_views:
        raise MpeError(f"{projections_source}: {len(projections)} matrices for {obs.n_views} views")
    names = [str(view.get("name", k)) for k, view in enumerate(views)]
    if solver in COLMAP_SOLVERS:
        _check_colmap(source, solver, camera, loss, projections, start, outlier_threshold)
        start = "own"  # COLMAP starts from its own initial pair
    file_start = _file_start(views, obs, source, start, objective, camera, projections,
                             principal_point)
    several = any("camera" in view for view in views)  # photos of several cameras, a focal each
    return Problem(obs, ids, solver, loss, random_state, objective, camera, projections,
                   float(outlier_threshold), principal_point, names, notes, file_start,
                   _first(views, "image_size"), _first(views, "focal_px"),
                   np.array([view["camera"] for view in views]) if several else None,
                   np.array([view["image_size"] for view in views]) if several else None,
                   np.array([view["offset"] for view in views], dtype=float) if several else None,
                   None if scratch is None else Path(scratch))


def _first(views, key):
    """A photo set's shared value (image size, EXIF focal length), or None."""
    return views[0].get(key) if views else None


def _loss_for(views, objective: str, solver: str) -> str:
    """The default loss: soft_l1 (scale 1 px) for bundle adjustment of SIFT
    tracks from photos or a COLMAP database, whose matches hold near misses
    within any threshold's reach (COLMAP's own bundle adjustment of them is
    robust too); l2 for everything else."""
    from_matcher = bool(views) and all("matches" in view for view in views)
    return "soft_l1" if objective == "reprojection" and solver == "bundle" and from_matcher else "l2"


def _solver_for(objective: str, solver: str | None) -> str:
    """The solver of ``objective``: refine for the stress, bundle adjustment for
    the reprojection error, unless one of its own is named."""
    if solver is None:
        return "refine" if objective == "stress" else "bundle"
    if objective == "stress" and solver in REPROJECTION_SOLVERS:
        raise MpeError(f"solver='{solver}' minimises the reprojection error; the stress takes "
                       "a stress solver (`mpe3d solvers`)")
    if objective == "reprojection" and solver not in REPROJECTION_SOLVERS:
        raise MpeError(f"solver='{solver}' is a stress solver; the reprojection objective takes "
                       f"{' or '.join(REPROJECTION_SOLVERS)} (or give objective='stress')")
    return solver


def _check_colmap(source, solver, camera, loss, projections, start, outlier_threshold):
    """What COLMAP's mappers cannot be asked (:data:`~mpe3d.solvers.sfm.colmap_mapper.COLMAP_TAKES`)."""
    for flag, value in (("camera", camera), ("loss", loss), ("start", start or "own"),
                        ("outlier_threshold", outlier_threshold)):
        reason = colmap_mapper.refused(flag, value)
        if reason is not None:
            raise MpeError(f"{flag}={value!r}: solver='{solver}': {reason}")
    if projections is not None:
        raise MpeError(f"{source}: solver='{solver}' estimates the cameras; known projections "
                       "are for solver='bundle'")


def _file_start(views, obs, source, start, objective, camera, projections, principal_point):
    """(X, radial cameras) from a Bundler or BAL file's values, when it has them
    and ``start`` does not say "own"."""
    has = all("start_camera" in view for view in views)
    if start == "file" and not has:
        raise MpeError(f"{source}: start='file' needs cameras and points in the input "
                       "(a Bundler .out or BAL file); this one has none")
    if start == "own" or not has:
        return None
    for flag, value, wanted in (("objective", objective, "reprojection"),
                                ("camera", camera, "radial")):
        if value != wanted and not (flag == "camera" and value == "auto"):
            raise MpeError(f"{source}: the file's cameras are a start for camera='radial' and "
                           f"the reprojection objective, not {flag}='{value}'; start='own' "
                           "solves from mpe3d's own start")
    if projections is not None or principal_point is not None:
        raise MpeError(f"{source}: the file gives the cameras (principal point at the image "
                       "centre); start='own' to give projections or a principal point")
    X = np.zeros((obs.n_points, 3))
    for view, seen in zip(views, obs.views):
        X[seen.ids] = view["start_points"]
    cams = [view["start_camera"] for view in views]
    cameras = radial_cameras(np.stack([c["rotation"] for c in cams]),
                             np.stack([c["translation"] for c in cams]),
                             np.array([c["focal"] for c in cams]),
                             np.stack([c["distortion"] for c in cams]))
    return X, cameras


def _warm_during_extraction() -> None:
    """A folder of photos: bundle adjustment's kernels load while COLMAP
    extracts features (its C++ lets go of the GIL), not after."""
    from mpe3d.solvers import warmup

    warmup.warm_in_background("l2", only=bundle.KERNELS)


def solve_problem(problem: Problem) -> Result:
    """Solve a prepared problem and report on the result."""
    from mpe3d.solvers import warmup

    if problem.objective == "stress":  # compiled before the clock
        warmup.warm(problem.loss)
    else:
        warmup.warm("l2", only=bundle.KERNELS)
    start = time.perf_counter()
    with collect_notes(labels=problem.ids) as notes:  # notes about the input go in the report
        if problem.objective == "reprojection":
            tracks = bundle.Tracks.from_observations(problem.observations)
            fit = _solve_reprojection(problem, tracks)
        else:
            # refine's rejection rounds are its outlier test: inf keeps every observation
            options = {"loss": problem.loss,
                       "outliers": "reject" if np.isfinite(problem.outlier_threshold) else "keep"} \
                if problem.solver == "refine" else {}
            fit = solvers.solve(problem.solver, problem.observations,
                                random_state=problem.random_state, **options)
    runtime = time.perf_counter() - start
    warnings = problem.notes + notes + stop_notes(fit)
    if problem.objective == "reprojection":
        return reprojection_result(problem, tracks, fit, runtime, warnings)
    return stress_result(problem, fit, runtime, warnings)


def _seed(random_state) -> int:
    """An integer seed from ``random_state`` (an int, or a Generator drawn once)."""
    return int(random_state if not isinstance(random_state, np.random.Generator)
               else random_state.integers(2 ** 31))


def _solve_reprojection(problem: Problem, tracks):
    check_geometry(problem.observations)  # one line for what cannot determine a shape
    seed = _seed(problem.random_state)
    if problem.solver in COLMAP_SOLVERS:
        from mpe3d.solvers import threads

        several = problem.view_cameras is not None
        return colmap_mapper.colmap_map(tracks, camera=problem.camera,
                                        principal_point=problem.principal_point,
                                        image_size=problem.image_sizes if several else problem.image_size,
                                        focal=problem.focal, seed=seed, threads=threads.count(),
                                        view_cameras=problem.view_cameras, scratch=problem.scratch,
                                        mapper=COLMAP_SOLVERS[problem.solver])
    if problem.cameras is not None:
        return bundle.known_cameras(tracks, problem.cameras, loss=problem.loss,
                                    outlier_threshold=problem.outlier_threshold)
    if problem.start is not None:
        return bundle.from_start(tracks, *problem.start, loss=problem.loss,
                                 outlier_threshold=problem.outlier_threshold, random_state=seed)
    if problem.view_cameras is not None:  # photos of several cameras: a focal length each
        return camera_groups.bundle_adjust_cameras(tracks, problem.view_cameras, problem.camera,
                                                   loss=problem.loss, outlier_threshold=problem.outlier_threshold,
                                                   principal_point=problem.principal_point, random_state=seed)
    return bundle.bundle_adjust(tracks, problem.camera, loss=problem.loss,
                                outlier_threshold=problem.outlier_threshold,
                                principal_point=problem.principal_point, focal=problem.focal,
                                random_state=seed)


def stop_notes(fit) -> list[str]:
    """A line when the solve stopped at its iteration cap instead of converging."""
    converged = getattr(fit, "converged", None)
    if converged is None:  # a stress solver: its termination says
        text = str(fit.termination).lower()
        converged = not ("limit" in text or "max_iter" in text)
    return [] if converged else [f"the solve did not converge ({fit.termination}): the cloud "
                                 "may be short of the optimum"]


def reconstruct(views: Sequence[dict] | str | Path, projections=None, solver: str | None = None,
                loss: str | None = None, random_state=0, objective: str | None = None,
                camera: str = "auto", missing=None,
                outlier_threshold: float = bundle.OUTLIER_THRESHOLD, principal_point=None,
                start: str | None = None, matches: str = DEFAULT_MATCHES, scratch=None) -> Result:
    """Rebuild a 3D cloud from user views.

    Parameters
    ----------
    views : a path or a list of ``{"ids", "xy" | "dist"}`` dicts
        What each view saw: its point ids and their 2D coordinates or distance
        matrix. A path: CSV, NPZ, JSON, a folder of .npz, a COLMAP model, a
        Bundler/BAL/VGG file, a folder of photos (SIFT features and matches
        by pycolmap) or a COLMAP ``database.db``.
    projections : None, a path, or an array of K 2x3 / 3x3 / 3x4 matrices, default None
        Known cameras (the fixed setting): orthographic rows or rotations, or
        3x4 pinhole matrices (reprojection only). None estimates them.
    solver : str or None, default None
        Who minimises the objective. The stress: any registered solver
        (``mpe3d solvers``, a plug-in's included; None: "refine"). The
        reprojection error: "bundle" (mpe3d's bundle adjustment; None),
        "colmap" (COLMAP's geometric verification and incremental mapper on
        the same tracks, through pycolmap) or "colmap_global" (the same
        verification and COLMAP's global mapper, GLOMAP's).
    loss : {None, "l2", "huber", "soft_l1", "cauchy"}, default None
        rho of the squared residual (reprojection, scale 1 px), or refine's loss
        of the stress (l2, huber, soft_l1). None: soft_l1 for bundle
        adjustment of tracks from photos or a COLMAP database, l2 otherwise.
    random_state : int >= 0 or Generator, default 0
    objective : {None, "reprojection", "stress"}, default None
        None: the reprojection error for coordinates (bundle adjustment)
        unless a stress solver is named, the 3DMPE stress (paper Eq. 1) for
        distance matrices.
    camera : {"auto", "orthographic", "scaled", "perspective", "radial"}, default "auto"
        The camera model of the reprojection objective; "auto" fits the scaled
        (weak-perspective) and the pinhole camera and keeps the pinhole when it
        explains the keypoints clearly better, and then the radial one when
        that is clearly better still. "radial" adds radial distortion
        k1, k2 (one lens for all views), estimated from the pinhole's fit.
    missing : None or (x, y), default None
        Observations at exactly (x, y) are markers for "not seen" and dropped.
    outlier_threshold : float, default 20
        Reprojection: observations beyond this many robust sigmas are taken for
        wrong matches and dropped (listed in the report); ``inf`` keeps all,
        and with the stress objective turns refine's rejection rounds off.
    principal_point : None or (x, y), default None
        The pinhole camera's principal point in pixels (the image centre);
        None takes the centre of the keypoints' bounding box.
    start : {None, "file", "own"}, default None
        Where bundle adjustment starts: "file" from the cameras (f, k1, k2 per
        view) and points of a Bundler or BAL input, "own" from mpe3d's start;
        None: the file's when it has them.
    matches : {"raw", "verified"}, default "raw"
        Photos and COLMAP databases: the tracks join the matcher's raw
        matches (mpe3d finds the wrong ones itself) or only those COLMAP's
        geometric verification kept.
    scratch : None or a folder, default None
        Photos and solver="colmap" or "colmap_global": where COLMAP's database is written (its
        free space checked against an estimate first); None: the system's
        temporary folder.
    """
    return solve_problem(prepare(views, projections, solver, loss, random_state, objective, camera,
                         missing, outlier_threshold, principal_point, start, matches, scratch))
