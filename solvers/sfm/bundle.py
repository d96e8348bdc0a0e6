"""Keypoints: minimise the reprojection error over the 3D points and the cameras.

When views come as 2D coordinates (matched keypoints, in pixels), the problem
they pose is bundle adjustment, not the distance stress of paper Eq. 1:

    E(X, C) = sum_t rho(||u_k(x_i; C_k) - z_t||^2)

over the observations t = (view k, point i, 2D point z_t), for a camera model
u (:mod:`mpe3d.solvers.sfm.cameras`) with analytic Jacobians. It is solved by
Levenberg-Marquardt with the points eliminated (:mod:`.adjust`: the Schur
complement, a 3x3 block per point, a dense K * (5..7) camera system), bundle
adjustment's standard solver. ``scipy.optimize.least_squares`` with the same
sparse Jacobian reaches the same optimum but took 43 s on VGG's dino tracks,
where this takes 0.3 s.

:func:`bundle_adjust` is a short sequence of stages (:mod:`.stages`), each
run when a cheap test says the data need it, each recorded with its reason
in the result's ``stages``:

1. suspects: two views at a time flag likely wrong matches and tell the
   keypoints' noise, and how far they are from any affine camera;
2. the camera model: the affine start and scaled fit (the scaled camera's
   fit, a pinhole's start or rival), the pinhole (a first opinion, a second
   only when the first is doubtful), the lens (auto: by an information
   criterion);
3. wrong matches (:func:`.outliers.peel_outliers`): peeled off against a
   robust residual scale and the problem solved again until none is left,
   then what the fit explains taken back;
4. the final adjustment: the points of weak geometry (:func:`.support.weak_points`)
   left out of it and placed under its cameras, points seen once on their rays.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.solvers.degenerate import warn
from mpe3d.solvers.linalg import elongation, sum_by
from mpe3d.solvers.sfm import stages
from mpe3d.solvers.sfm.adjust import LMOptions, adjust, one_blas_thread
from mpe3d.solvers.sfm.camera_fits import FITTERS
from mpe3d.solvers.sfm.cameras import (
    MATRIX,
    PINHOLES,
    Cameras,
    affine_cameras,
    known_matrices,
)
from mpe3d.solvers.sfm.outliers import (
    OUTLIER_THRESHOLD,
    peel_outliers,
    without_outliers,
    without_runaways,
)
from mpe3d.solvers.sfm.stages import BundleOptions, BundleState, Stage
from mpe3d.solvers.sfm.support import (
    ELONGATION,
    MIN_RAY_ANGLE,
    informative,
    mean_by_view,
    weak_points,
)
from mpe3d.solvers.sfm.tracks import EXACT_RMS, Tracks, image_size, residual_lengths, rms
from mpe3d.solvers.sfm.triangulation import (
    dlt_rows,
    least_squares_points,
)

# The compiled kernels loaded before a bundle adjustment's clock: the SfM
# stack's own (warmup.warm(only=KERNELS) loads no stress kernel; the affine
# factorisation's, 0.3 s to load, only when the affine start runs)
KERNELS = ("mpe3d.solvers.sfm.",)
_TRANSLATION_SWEEPS = 3  # known orthographic cameras: points and image origins in turn
_PLACING_STEPS = 10  # Gauss-Newton steps that put a point seen once on its ray
DISAGREE_RATIO = 0.5  # another model this much better is said


@dataclass
class BundleResult:
    """Points, cameras and how well they explain the keypoints."""

    points: np.ndarray  # (N, 3)
    cameras: Cameras
    residuals: np.ndarray  # (T, 2), pixels, for every observation
    dropped: np.ndarray  # (T,) bool: observations taken for wrong matches
    counted: np.ndarray  # (T,) bool: kept observations of placed points, what rms() measures
    converged: bool
    iterations: int  # Levenberg-Marquardt iterations of the final solve
    termination: str
    affine_rms: float  # RMS of the affine factorisation, a floor for any affine camera (NaN: not run)
    camera: str = "scaled"  # the model fitted (auto resolved)
    placed: np.ndarray | None = None  # (N,) bool: points whose depth the views fix
    weak: np.ndarray | None = None  # (N,) bool: of the others, those placed but of weak geometry
    registered: np.ndarray | None = None  # (K,) bool: views with a pose (False: left out)
    rms_by_camera: dict[str, float] = field(default_factory=dict)  # each model fitted, on what it rests on
    rms_history: np.ndarray = field(default_factory=lambda: np.zeros(0))  # of the final solve
    stages: tuple[Stage, ...] = ()  # what ran, and why
    noise: float = float("nan")  # the keypoints' noise, pixels (two views at a time; NaN: unknown)
    affine_misfit: float = float("nan")  # their distance to affine epipolar geometry, pixels
    seconds: dict[str, float] = field(default_factory=dict)  # a mapper's phases (COLMAP's)

    def rms(self, rows=None) -> float:
        """sqrt(mean ||r_t||^2) in pixels over ``rows``, by default the kept
        observations of the placed points (an unplaced point's depth, and so
        its residual, is a guess)."""
        return rms(self.residuals[self.counted if rows is None else rows])


@one_blas_thread
def bundle_adjust(tracks: Tracks, camera: str = "auto", *, principal_point=None,
                  shared_focal: bool = True, focal: float | None = None, loss: str = "l2",
                  loss_scale: float = 1.0, outlier_threshold: float = OUTLIER_THRESHOLD,
                  max_iter: int = 100, tol: float = 1e-10, random_state: int = 0) -> BundleResult:
    """Points and cameras of model ``camera`` that minimise the reprojection error.

    Parameters
    ----------
    tracks : Tracks
        The observations, in pixels.
    camera : {"auto", "orthographic", "scaled", "perspective", "radial"}, default "auto"
        "auto" decides in stages (:mod:`.stages`): the pinhole where two views
        at a time already show perspective; else the scaled (weak-perspective)
        camera where it fits at the keypoints' noise level, or the pinhole
        where it explains them clearly better (median residual below
        ``AUTO_RATIO`` times the weak perspective's); then ``radial`` when
        the lens's distortion shows by an information criterion
        (:func:`.stages.lens`). "radial" is the pinhole with radial
        distortion k1, k2, fitted from the pinhole's solution.
    principal_point : (2,) or None, default None
        Pinholes only; None takes the centre of the keypoints' bounding box.
    shared_focal : bool, default True
        Pinholes only: one focal length (and for radial one k1, k2: one lens)
        for all views, or one per view.
    focal : float or None, default None
        Pinholes only: a prior focal length in pixels (a photo's EXIF), the
        pinhole starts' focal length; None: the starts' own guesses.
    loss : {"l2", "huber", "soft_l1", "cauchy"}, default "l2"
        rho of the squared residual length, with ``loss_scale`` in pixels.
    outlier_threshold : float, default OUTLIER_THRESHOLD
        An observation whose residual is longer than this many robust sigmas
        (from the median residual length) is taken for a wrong match, dropped,
        and the problem solved again, until none is left; ``inf`` keeps all.
    max_iter : int, default 100
        Levenberg-Marquardt iterations per solve.
    tol : float, default 1e-10
        Stop when an iteration lowers the cost by less than this fraction.
    random_state : int >= 0, default 0
        The seed of every random choice (the two-view tests' and the starts'
        RANSACs, the robust triangulation's samples).
    """
    state = BundleState(tracks, BundleOptions(camera, None if principal_point is None else tuple(principal_point),
                                              shared_focal, focal, loss, loss_scale, outlier_threshold, max_iter,
                                              tol, random_state))
    stages.suspects(state)
    return _final(state, _camera_model(state))


def _camera_model(state: BundleState) -> str:
    """The fits the camera asked for needs, and for "auto" the model kept."""
    asked = state.options.camera
    if asked in ("orthographic", "scaled"):
        stages.affine_start(state, short=False)
        if asked == "orthographic":
            _orthographic(state)
        return asked
    if asked == "auto" and not stages.perspective_shows(state):
        stages.affine_start(state, short=False)
        why = stages.at_noise(state, "scaled")
        if why:
            state.record("pinhole", False, why)
            return "scaled"
    stages.pinhole(state)
    return _weak_or_pinhole(state) if asked == "auto" else asked


def _weak_or_pinhole(state: BundleState) -> str:
    """camera="auto" after the pinhole: the pinhole when the scaled fit was not
    needed (two views showed perspective) or when the pinhole's median
    residual is under AUTO_RATIO times the scaled fit's, on the observations
    both rest on; the scaled camera otherwise (solved to the end by the
    rounds of wrong matches if its fit was only a start)."""
    if "scaled" not in state.fits:
        return "perspective"
    return "perspective" if state.median("perspective") < stages.AUTO_RATIO * state.median("scaled") else "scaled"


def _orthographic(state: BundleState) -> None:
    """The orthographic fit, from the scaled one with one scale for all views."""
    tracks, used, lm = state.tracks, state.used, state.options.lm
    fit = FITTERS["orthographic"](*state.fits["scaled"][:2], tracks.subset(used), None, True, lm)
    fit, runaways = without_runaways(fit, tracks, used, lm)
    state.flagged |= runaways  # suspects, as the two-view test's are
    state.fits["orthographic"], state.rows["orthographic"] = fit, used


def _final(state: BundleState, camera: str) -> BundleResult:
    """Wrong matches peeled off the kept model's fit, and the final adjustment."""
    tracks, options = state.tracks, state.options
    rms_by_camera = {fitted: state.rms(fitted) for fitted in state.fits}
    model = "perspective" if camera == "radial" else camera  # the lens comes after the wrong matches
    if not np.isfinite(rms_by_camera[model]):
        raise MpeError("the keypoints do not determine a 3D shape: no start gives finite "
                       "cameras (a planar scene, or too few points shared by the views?)")
    _say_if_the_data_disagree(state, model)
    fit = state.fits[model]
    registered = state.registered if camera in PINHOLES else np.ones(tracks.n_views, dtype=bool)
    flagged = state.flagged.copy()
    if camera in PINHOLES and options.robust:
        flagged |= ~state.rows[model]  # an observation a pinhole start filtered is a suspect
    elif camera in PINHOLES and (state.used & registered[tracks.view] & ~state.rows[model]).any():
        # every observation kept: the fit is solved on all of its views'
        fit = adjust(*fit[:2], tracks.subset(state.used & registered[tracks.view]), options.lm)
    inside = registered[tracks.view]
    sub = tracks if registered.all() else tracks.subset(inside)
    fit, dropped = _wrong_matches(state, fit, sub, flagged[inside], state.solved.get(model, True))
    if camera in PINHOLES and (camera == "radial" or options.camera == "auto"):
        fit, dropped, camera = _lens(state, fit, sub, dropped, camera, rms_by_camera)
    result = _result(fit, sub, dropped, camera, options.max_iter, state.affine_rms, rms_by_camera,
                     options.lm, registered, tuple(state.stages))
    result.noise, result.affine_misfit = state.noise, state.affine
    return result if registered.all() else _widened(result, tracks, inside)


def _wrong_matches(state: BundleState, fit, tracks, flagged, solved):
    """:func:`.outliers.peel_outliers` of ``fit``, recorded as a stage."""
    options, start = state.options, time.perf_counter()
    fit, dropped = peel_outliers(fit, tracks, flagged, options.outlier_threshold, options.lm,
                                 options.random_state, solved)
    state.record("wrong matches", options.robust, f"{int(dropped.sum())} observations dropped"
                 if options.robust else "outlier_threshold=inf keeps every observation", start)
    return fit, dropped


def _lens(state: BundleState, fit, tracks, dropped, camera, rms_by_camera):
    """The radial camera asked for, or for "auto" the lens when the keypoints
    the pinhole kept show one (:func:`.stages.lens`): fitted on them, and
    its own wrong matches peeled off. Returns the fit, the observations
    dropped and the camera."""
    if not state.options.shared_focal and camera != "radial":
        state.record("lens", False, "one focal length per view: no shared lens to fit")
        return fit, dropped, camera
    kept = informative(tracks, ~dropped)
    radial = stages.lens(state, fit, tracks, kept, asked=camera == "radial")
    if radial is None:
        return fit, dropped, camera
    rms_by_camera["radial"] = float(np.sqrt(np.mean(residual_lengths(*radial[:2], tracks, kept) ** 2)))
    fit, dropped = _wrong_matches(state, radial, tracks, dropped, False)  # fitted loosely
    return fit, dropped, "radial"


def _widened(result: BundleResult, tracks, inside) -> BundleResult:
    """A result of the registered views' observations over every observation:
    the others' residuals NaN, neither dropped nor counted."""
    residuals = np.full((len(tracks.view), 2), np.nan)
    residuals[inside] = result.residuals
    dropped, counted = np.zeros(len(tracks.view), dtype=bool), np.zeros(len(tracks.view), dtype=bool)
    dropped[inside], counted[inside] = result.dropped, result.counted
    result.residuals, result.dropped, result.counted = residuals, dropped, counted
    return result


def _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms_by_camera, lm: LMOptions,
            registered=None, done=()) -> BundleResult:
    """The result of a fit: weak points out of it, points seen once placed on
    their rays, every residual."""
    start = time.perf_counter()
    fit, placed, narrow, far = _without_weak(fit, tracks, dropped, lm)
    X, cameras, history, converged = fit
    # a narrow point keeps the adjustment's depth (its best guess, and its rays'
    # fit); a far one has none worth keeping: it goes to the cloud's depth
    X = place_unplaced(X, cameras, tracks, placed & ~far, ~dropped)
    weak = narrow | far
    _say_if_depth_is_free(X, placed, weak, camera)
    placed &= ~weak
    residuals = cameras.project(X, tracks.view, tracks.point) - tracks.z
    final = Stage("final adjustment", True, f"{int(weak.sum())} points of weak geometry set aside, "
                  f"{int((~placed & ~weak).sum())} unplaced", time.perf_counter() - start)
    return BundleResult(points=X, cameras=cameras, residuals=residuals, dropped=dropped,
                        counted=_counted(dropped, placed[tracks.point]),
                        converged=converged, iterations=len(history) - 1,
                        termination="converged" if converged else f"stopped at max_iter={max_iter}",
                        affine_rms=affine_rms, camera=camera, placed=placed, weak=weak,
                        registered=np.ones(tracks.n_views, dtype=bool) if registered is None else registered,
                        rms_by_camera=rms_by_camera, rms_history=history, stages=(*done, final))


def _counted(dropped, placed_rows):
    """The observations rms() measures: the kept ones of placed points, or all
    kept ones when no point is placed (views that fix no depth at all)."""
    counted = ~dropped & placed_rows
    return counted if counted.any() else ~dropped


def _without_weak(fit, tracks, dropped, lm: LMOptions):
    """The fit solved again without the points of weak geometry, as COLMAP
    filters its points before its last adjustment: their rays, nearly
    parallel, pull on the cameras for no depth (a point 7e8 away among COLMAP's
    250 photos). Returns the fit, the points placed before, and the ``narrow``
    and ``far`` masks."""
    weak, placed, narrow, far = weak_points(fit, tracks, ~dropped)
    if not weak.any():
        return fit, placed, narrow, far
    strong = informative(tracks, ~dropped & ~weak[tracks.point])
    again = adjust(*fit[:2], tracks.subset(strong), lm)
    return again._replace(history=np.concatenate([fit.history, again.history[1:]])), placed, narrow, far


def _say_if_depth_is_free(X, placed, weak, camera) -> None:
    """One line when the views fix the depth of too few points, or of none
    but a cloud far longer than wide: their baseline is too small."""
    fixed = placed & ~weak
    if placed.sum() <= 3:
        return
    if weak.sum() > placed.sum() / 2:
        why = (f"{int(weak.sum())} of {int(placed.sum())} points' rays meet under "
               f"{MIN_RAY_ANGLE:g} degrees, left unplaced")
    elif fixed.sum() > 3 and elongation(X[fixed]) > ELONGATION:
        why = f"it is {elongation(X[fixed]):.3g} times longer than wide"
    else:
        return
    warn(f"the views do not determine the cloud's depth under the {camera} camera ({why}): "
         "their baseline is too small for it"
         + ("" if camera in PINHOLES else "; try camera='perspective'"))


@one_blas_thread
def known_cameras(tracks: Tracks, matrices: np.ndarray, *, loss: str = "l2",
                  loss_scale: float = 1.0, outlier_threshold: float = OUTLIER_THRESHOLD,
                  max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """The points (and each view's 2D translation) for known cameras: (K, 2, 3)
    orthonormal rows, an orthographic camera whose image origin is free, or
    (K, 3, 4) pinhole matrices, which fix everything but the points."""
    options = BundleOptions(loss=loss, loss_scale=loss_scale, outlier_threshold=outlier_threshold,
                            max_iter=max_iter, tol=tol)
    matrices = np.asarray(matrices, dtype=float)
    used = informative(tracks, np.ones(len(tracks.view), dtype=bool))
    sub = tracks.subset(used)
    if matrices.shape[1:] == (3, 4):
        cameras, frozen = known_matrices(matrices), None
        A, b = dlt_rows(matrices, sub.view, sub.z)
    else:
        cameras = affine_cameras("orthographic", matrices, np.ones(len(matrices)),
                                 np.zeros((len(matrices), 2)))
        frozen = np.zeros(cameras.vector().size, dtype=bool)
        frozen.reshape(len(matrices), -1)[:, :3] = True
        # z = P x + t is linear in (x, t): alternate the two, from t = the view means
        A, b = matrices[sub.view], sub.z
        for _ in range(_TRANSLATION_SWEEPS):
            X = least_squares_points(A, b - cameras.params[sub.view, 3:5], sub.point, sub.n_points)
            residual = sub.z - np.einsum("tij,tj->ti", A, X[sub.point])
            cameras.params[:, 3:5] = mean_by_view(residual, sub)
    if cameras.model == MATRIX:
        X = least_squares_points(A, b, sub.point, sub.n_points)
    lm = LMOptions(loss, loss_scale, max_iter, tol, frozen)
    fit = adjust(X, cameras, sub, lm)
    fit, dropped = without_outliers(fit, tracks, np.zeros(len(used), dtype=bool), options.outlier_threshold, lm)
    return _result(fit, tracks, dropped, cameras.model if cameras.model == MATRIX
                   else "orthographic", max_iter, float("nan"), {}, lm)


@one_blas_thread
def from_start(tracks: Tracks, X: np.ndarray, cameras: Cameras, *, loss: str = "l2",
               loss_scale: float = 1.0, outlier_threshold: float = OUTLIER_THRESHOLD,
               max_iter: int = 100, tol: float = 1e-10, random_state: int = 0) -> BundleResult:
    """Bundle adjustment from given points and cameras (a Bundler or BAL
    file's): every parameter free, wrong matches dropped as in
    :func:`bundle_adjust`, no start of ours tried."""
    lm = BundleOptions(loss=loss, loss_scale=loss_scale, outlier_threshold=outlier_threshold,
                       max_iter=max_iter, tol=tol, random_state=random_state).lm
    used = informative(tracks, np.ones(len(tracks.view), dtype=bool))
    if not np.all(np.isfinite(cameras.project(X, tracks.view[used], tracks.point[used]))):
        raise MpeError("the start puts points behind the cameras that see them: not a start "
                       "for these observations (try start='own')")
    fit = adjust(np.asarray(X, dtype=float), cameras, tracks.subset(used), lm)
    fit, dropped = peel_outliers(fit, tracks, np.zeros(len(used), dtype=bool), outlier_threshold, lm,
                                 random_state)
    return _result(fit, tracks, dropped, cameras.model, max_iter, float("nan"), {}, lm)


def _say_if_the_data_disagree(state: BundleState, camera: str) -> None:
    """One line when another camera model explains the keypoints far better
    (its median residual under DISAGREE_RATIO times the kept one's), or, for
    an affine camera, when two views at a time already show perspective."""
    median = {model: state.median(model) for model in state.fits}
    better = {model: value for model, value in median.items()
              if model != camera and value < DISAGREE_RATIO * median[camera]}
    if better:
        model = min(better, key=better.get)
        warn(f"the keypoints disagree with the {camera} camera: median residual "
             f"{median[camera]:.3g} px, against {better[model]:.3g} px with the {model} camera "
             f"(camera='{model}')")
    elif camera not in PINHOLES and stages.perspective_shows(state):
        warn(f"the keypoints disagree with the {camera} camera: two views at a time are "
             f"{state.affine:.3g} px from affine epipolar geometry, their noise is {state.noise:.3g} px "
             f"(camera='perspective')")


def place_unplaced(X, cameras, tracks, placed, kept):
    """Points kept in fewer than 2 views, or whose rays meet too narrowly
    (:func:`weak_geometry`), have no depth: each goes where its views put it
    at the depth of the cloud's centre (its other coordinates are
    the least-squares ones of the views it has)."""
    X = X.copy()
    centre = X[placed].mean(axis=0) if placed.any() else np.zeros(3)
    X[~placed] = centre
    lonely = ~placed[tracks.point] & kept
    if not lonely.any():
        return X
    # Gauss-Newton steps from the centre move x only across the view's rays: one
    # is exact for an affine camera; a pinhole's curved image takes a few (VGG's
    # house, every other view: 35 px off its ray after one)
    view, point, z = tracks.view[lonely], tracks.point[lonely], tracks.z[lonely]
    counts = np.maximum(np.bincount(point, minlength=tracks.n_points), 1)
    for _ in range(_PLACING_STEPS):
        r = cameras.project(X, view, point) - z
        if not np.all(np.isfinite(r)) or np.abs(r).max() <= EXACT_RMS * image_size(tracks):
            break
        d_x = cameras.jacobian_blocks(X, view, point)[0]
        step = np.einsum("tij,tj->ti", np.linalg.pinv(d_x), -r)
        X += sum_by(point, step, tracks.n_points) / counts[:, None]
    return X

