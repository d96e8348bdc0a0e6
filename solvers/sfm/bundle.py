"""Keypoints: minimise the reprojection error over the 3D points and the cameras.

When views come as 2D coordinates (matched keypoints, in pixels), the problem
they pose is bundle adjustment, not the distance stress of paper Eq. 1:

    E(X, C) = sum_t rho(||u_k(x_i; C_k) - z_t||^2)

over the observations t = (view k, point i, 2D point z_t), for a camera model
u (:mod:`mpe3d.solvers.sfm.cameras`) with analytic Jacobians. It is solved by
Levenberg-Marquardt with the points eliminated (the Schur complement: a 3x3
block per point, a dense K * (5..7) camera system), bundle adjustment's
standard solver. ``scipy.optimize.least_squares`` with the same sparse
Jacobian (trust-region reflective, LSMR) reaches the same optimum but took
43 s to converge on VGG's dino tracks, where this takes 0.3 s. The start
cannot blow up:

1. an affine factorisation with missing data (:mod:`.factorize`), grown from
   the best pair of views, from 1 and from 20 alternating sweeps, with a
   metric upgrade that is positive definite by construction: M = A A^T with
   A lower-triangular, fitted by least squares to the weak-perspective
   conditions (each view's two rows orthogonal and of equal length) from
   the linear solution and from the identity, the better one kept;
2. an incremental reconstruction (:mod:`.incremental`), grown from three
   views, robust at each step, which long sequences with missing data need
   (the global factorisation folds dino's turntable when 80 observations
   are removed);
3. a pinhole start grown view by view (:mod:`.pinhole_start`: an essential
   matrix's initial pair, then resection by P3P, as COLMAP grows its models),
   which close photos taken far apart need (the affine start folds there);
4. bundle adjustment of the ``scaled`` model from each affine start,
   scouted, the best one solved to the end; ``orthographic`` from it with one
   scale for all views; ``perspective`` from the scaled fit at several focal
   lengths and in both depth orders, against the grown pinhole: the grown
   one kept where it registers every view with a median residual no larger,
   or, leaving views out (then unregistered), with one under half.

Wrong matches are first suspected before any fit, two views at a time
(:mod:`.epipolar`) and by the incremental start, and left out of every fit;
then peeled off against a robust residual scale (the median residual length)
and the problem solved again, until none is left (:func:`without_outliers`);
last, the points with dropped observations are triangulated again robustly
under the final cameras, and what the fit explains is taken back
(:func:`_readmitted`). The points of weak geometry (:func:`weak_geometry`)
sit out the long solves (:func:`peel_outliers`) and are adjusted alone after them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.options import CAMERAS, REPROJECTION_LOSSES
from mpe3d.solvers.degenerate import warn
from mpe3d.solvers.linalg import elongation, sum_by
from mpe3d.solvers.sfm import incremental
from mpe3d.solvers.sfm.adjust import adjust, one_blas_thread
from mpe3d.solvers.sfm.camera_fits import FITTERS, grown_pinhole, scaled_fit
from mpe3d.solvers.sfm.cameras import (
    MATRIX,
    PINHOLES,
    Cameras,
    affine_cameras,
    known_matrices,
)
from mpe3d.solvers.sfm.epipolar import epipolar_outliers
from mpe3d.solvers.sfm.outliers import (
    OUTLIER_THRESHOLD,
    finite_threshold,
    peel_outliers,
    without_outliers,
    without_runaways,
)
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

START_ITERATIONS = 20  # the scaled fit's when it is only a pinhole's start
_TRANSLATION_SWEEPS = 3  # known orthographic cameras: points and image origins in turn
_PLACING_STEPS = 10  # Gauss-Newton steps that put a point seen once on its ray
AUTO_RATIO = 0.8  # camera="auto" keeps the pinhole below this share of the weak median residual
DISAGREE_RATIO = 0.5  # another model this much better is said
GROWN_RATIO = 0.5  # the grown pinhole, leaving views out, is kept below this share of the other's median


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
    affine_rms: float  # RMS of the affine factorisation, a floor for any camera model
    camera: str = "scaled"  # the model fitted (auto resolved)
    info: dict[str, Any] = field(default_factory=dict)

    def rms(self, rows=None) -> float:
        """sqrt(mean ||r_t||^2) in pixels over ``rows``, by default the kept
        observations of the placed points (an unplaced point's depth, and so
        its residual, is a guess)."""
        return rms(self.residuals[self.counted if rows is None else rows])


@one_blas_thread
def bundle_adjust(tracks: Tracks, camera: str = "auto", *, principal_point=None,
                  shared_focal: bool = True, loss: str = "l2", loss_scale: float = 1.0,
                  outlier_threshold: float = OUTLIER_THRESHOLD, max_iter: int = 100,
                  tol: float = 1e-10) -> BundleResult:
    """Points and cameras of model ``camera`` that minimise the reprojection error.

    Parameters
    ----------
    tracks : Tracks
        The observations, in pixels.
    camera : {"auto", "orthographic", "scaled", "perspective", "radial"}, default "auto"
        "auto" fits ``scaled`` and ``perspective`` and keeps the pinhole camera
        when it explains the keypoints clearly better (median residual below
        ``AUTO_RATIO`` times the weak perspective's), and then ``radial`` when
        it is as clearly better than the pinhole (a real lens). "radial" is the pinhole
        with radial distortion k1, k2, fitted from the pinhole's solution.
    principal_point : (2,) or None, default None
        Pinholes only; None takes the centre of the keypoints' bounding box.
    shared_focal : bool, default True
        Pinholes only: one focal length (and for radial one k1, k2: one lens)
        for all views, or one per view.
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
    """
    CAMERAS.check("camera", camera)
    REPROJECTION_LOSSES.check("loss", loss)
    # the Levenberg-Marquardt options every adjust() of this problem shares
    lm_options = dict(loss=loss, loss_scale=loss_scale, max_iter=max_iter, tol=tol)
    flagged = _epipolar_flags(tracks, outlier_threshold)
    used = informative(tracks, ~flagged)
    # the pinhole grown view by view, where a pinhole may be kept
    early = _grown(tracks, used, principal_point, lm_options) \
        if camera in ("auto", *PINHOLES) and shared_focal and np.isfinite(outlier_threshold) else None
    every_view = early is not None and early[1].all()
    # a pinhole asked for, or grown over every view: the scaled fit is its start
    # or its rival, which needs no more than START_ITERATIONS to be judged (the
    # weak perspective of pinhole photos converges slowly: COLMAP's 250-photo
    # spiral ran to 100 iterations, 12 s, for the same pinhole); it is solved
    # to the end if it is kept
    short = camera in PINHOLES or (camera == "auto" and every_view)
    start_options = {**lm_options, "max_iter": min(lm_options["max_iter"], START_ITERATIONS)} \
        if short else lm_options
    grown = incremental.incremental_start(tracks.subset(used), finite_threshold(outlier_threshold))
    if grown is not None and np.isfinite(outlier_threshold):  # its left-outs are suspects too
        flagged[np.flatnonzero(used)[grown.left_out]] = True
        used = informative(tracks, ~flagged)
    fit, affine_rms = scaled_fit(tracks.subset(used), start_options,
                              None if grown is None else grown[:2])  # (X, cameras)
    # The models are compared on the same observations, before any is dropped:
    # a weak-perspective misfit of perspective data is no wrong match.
    fits = {"scaled": fit}
    exact = _rms_of(fit, tracks, used) <= 1e3 * EXACT_RMS * image_size(tracks)
    if exact and camera == "auto":  # orthographic views, noise-free: nothing fits better
        camera = "scaled"
    wanted = ("scaled", "perspective") if camera == "auto" else (camera,)
    others = {"orthographic": ("scaled", "perspective"), "scaled": ("perspective",),
              "perspective": ("scaled",), "radial": ("scaled",)}
    # the radial camera starts from the pinhole's fit, so that one comes first
    needed = ("perspective",) if camera == "radial" else ()
    # the observations the pinholes rest on: all, or those of the grown start's model
    registered, in_model = np.ones(tracks.n_views, dtype=bool), np.ones(len(tracks.view), dtype=bool)
    for model in dict.fromkeys(needed + wanted + ((), others.get(camera, ()))[not exact]):
        if model == "perspective" and early is not None:
            fits[model], registered, in_model = _perspective_fit(fit, early, tracks, used, principal_point,
                                                                 lm_options)
        elif model not in fits:
            rows = used & in_model if model in PINHOLES else used
            fits[model] = FITTERS[model](*(fits["perspective"] if model == "radial" else fit)[:2],
                                          tracks.subset(rows), principal_point, shared_focal,
                                          lm_options)
            fits[model], runaways = without_runaways(fits[model], tracks, rows, lm_options)
            flagged |= runaways  # suspects, as the two-view test's are
    # a model is judged on what it rests on: every observation, or the grown start's model
    rows = {model: used & in_model if model in PINHOLES else used for model in fits}
    rms = {model: _rms_of(f, tracks, rows[model]) for model, f in fits.items()}
    # the models are judged by their median residual, which wrong matches do not sway
    median = {model: _median_of(f, tracks, rows[model]) for model, f in fits.items()}
    if not np.isfinite(rms[camera if camera != "auto" else "scaled"]):
        raise MpeError("the keypoints do not determine a 3D shape: no start gives finite "
                       "cameras (a planar scene, or too few points shared by the views?)")
    if camera == "auto":
        camera = "perspective" if median["perspective"] < AUTO_RATIO * median["scaled"] \
            else "scaled"
        if camera == "perspective" and shared_focal:  # and the lens, as COLMAP's SIMPLE_RADIAL has one
            camera = _with_lens(fits, rms, median, rows["perspective"], tracks, principal_point, lm_options)
    _say_if_the_data_disagree(camera, median)
    if camera in PINHOLES:
        flagged |= ~in_model  # a filtered observation is a suspect
    else:
        registered = np.ones(tracks.n_views, dtype=bool)
        if short and camera == "scaled":  # kept after a short solve: solved to the end
            fits[camera] = adjust(*fits[camera][:2], tracks.subset(used), **lm_options)
    if registered.all():
        fit, dropped = peel_outliers(fits[camera], tracks, flagged, outlier_threshold, lm_options)
        return _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, lm_options,
                       registered)
    # the views left out stay out: the rest is solved on their observations alone
    inside = registered[tracks.view]
    fit, dropped = peel_outliers(fits[camera], tracks.subset(inside), flagged[inside], outlier_threshold,
                                 lm_options)
    result = _result(fit, tracks.subset(inside), dropped, camera, max_iter, affine_rms, rms, lm_options,
                     registered)
    return _widened(result, tracks, inside)


def _widened(result: BundleResult, tracks, inside) -> BundleResult:
    """A result of the registered views' observations over every observation:
    the others' residuals NaN, neither dropped nor counted."""
    residuals = np.full((len(tracks.view), 2), np.nan)
    residuals[inside] = result.residuals
    dropped, counted = np.zeros(len(tracks.view), dtype=bool), np.zeros(len(tracks.view), dtype=bool)
    dropped[inside], counted[inside] = result.dropped, result.counted
    result.residuals, result.dropped, result.counted = residuals, dropped, counted
    return result


def _with_lens(fits, rms, median, rows, tracks, principal_point, lm_options) -> str:
    """"radial" where the pinhole with radial distortion (fitted from the
    pinhole's solution, on what it rests on) explains the keypoints clearly
    better (median residual under AUTO_RATIO times the pinhole's: a real
    lens, 11 photos of a castle: 2.04 -> 0.70 px RMS), else "perspective"."""
    fit = FITTERS["radial"](*fits["perspective"][:2], tracks.subset(rows), principal_point, True, lm_options)
    fits["radial"] = fit
    rms["radial"], median["radial"] = _rms_of(fit, tracks, rows), _median_of(fit, tracks, rows)
    return "radial" if median["radial"] < AUTO_RATIO * median["perspective"] else "perspective"


def _grown(tracks, used, principal_point, lm_options):
    """:func:`.camera_fits.grown_pinhole` on the ``used`` observations: its fit,
    its (K,) registered views and the (T,) observations of its model, or None."""
    grown = grown_pinhole(tracks.subset(used), principal_point, lm_options)
    if grown is None:
        return None
    in_model = np.zeros(len(tracks.view), dtype=bool)  # grown[2]: over the used rows
    in_model[np.flatnonzero(used)[grown[2]]] = True
    return grown[0], grown[1], in_model


def _perspective_fit(scaled, grown, tracks, used, principal_point, lm_options):
    """The better of two pinholes: the one from the ``scaled`` fit (several focal
    lengths, both depth orders) and the one grown view by view
    (:func:`.camera_fits.grown_pinhole`; close photos from far apart fold the
    affine start, and a guessed principal point can mislead the grown one). The
    grown one is kept when it registers every view with a median residual no
    larger on the observations both rest on, or, leaving views out, with one
    under GROWN_RATIO times the other's. Returns the fit, the (K,) views it
    registers and the (T,) observations it rests on."""
    everything = np.ones(tracks.n_views, dtype=bool), np.ones(len(tracks.view), dtype=bool)
    fit = FITTERS["perspective"](*scaled[:2], tracks.subset(used), principal_point, True, lm_options)
    fit, _ = without_runaways(fit, tracks, used, lm_options)
    if grown is None:
        return fit, *everything
    other, registered, in_model = grown
    theirs, ours = _median_of(other, tracks, in_model & used), _median_of(fit, tracks, in_model & used)
    if theirs <= ours if registered.all() else theirs < GROWN_RATIO * ours:
        return grown
    return fit, *everything


def _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, lm_options,
            registered=None) -> BundleResult:
    """The result of a fit: weak points out of it, points seen once placed on
    their rays, every residual."""
    fit, placed, narrow, far = _without_weak(fit, tracks, dropped, lm_options)
    X, cameras, history, converged = fit
    # a narrow point keeps the adjustment's depth (its best guess, and its rays'
    # fit); a far one has none worth keeping: it goes to the cloud's depth
    X = place_unplaced(X, cameras, tracks, placed & ~far, ~dropped)
    weak = narrow | far
    _say_if_depth_is_free(X, placed, weak, camera)
    placed &= ~weak
    residuals = cameras.project(X, tracks.view, tracks.point) - tracks.z
    return BundleResult(points=X, cameras=cameras, residuals=residuals, dropped=dropped,
                        counted=_counted(dropped, placed[tracks.point]),
                        converged=converged, iterations=len(history) - 1,
                        termination="converged" if converged else f"stopped at max_iter={max_iter}",
                        affine_rms=affine_rms, camera=camera,
                        info={"rms_history": history, "rms_by_camera": rms, "placed": placed,
                              "weak": weak,
                              "registered": np.ones(tracks.n_views, dtype=bool) if registered is None
                              else registered})


def _counted(dropped, placed_rows):
    """The observations rms() measures: the kept ones of placed points, or all
    kept ones when no point is placed (views that fix no depth at all)."""
    counted = ~dropped & placed_rows
    return counted if counted.any() else ~dropped


def _without_weak(fit, tracks, dropped, lm_options):
    """The fit solved again without the points of weak geometry, as COLMAP
    filters its points before its last adjustment: their rays, nearly
    parallel, pull on the cameras for no depth (a point 7e8 away among COLMAP's
    250 photos). Returns the fit, the points placed before, and the ``narrow``
    and ``far`` masks."""
    weak, placed, narrow, far = weak_points(fit, tracks, ~dropped)
    if not weak.any():
        return fit, placed, narrow, far
    strong = informative(tracks, ~dropped & ~weak[tracks.point])
    again = adjust(*fit[:2], tracks.subset(strong), **lm_options)
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
    REPROJECTION_LOSSES.check("loss", loss)
    # the Levenberg-Marquardt options every adjust() of this problem shares
    lm_options = dict(loss=loss, loss_scale=loss_scale, max_iter=max_iter, tol=tol)
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
    fit = adjust(X, cameras, sub, **lm_options, frozen=frozen)
    fit, dropped = without_outliers(fit, tracks, np.zeros(len(used), dtype=bool),
                                     outlier_threshold, {**lm_options, "frozen": frozen})
    return _result(fit, tracks, dropped, cameras.model if cameras.model == MATRIX
                   else "orthographic", max_iter, float("nan"), {}, {**lm_options, "frozen": frozen})


@one_blas_thread
def from_start(tracks: Tracks, X: np.ndarray, cameras: Cameras, *, loss: str = "l2",
               loss_scale: float = 1.0, outlier_threshold: float = OUTLIER_THRESHOLD,
               max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """Bundle adjustment from given points and cameras (a Bundler or BAL
    file's): every parameter free, wrong matches dropped as in
    :func:`bundle_adjust`, no start of ours tried."""
    REPROJECTION_LOSSES.check("loss", loss)
    lm_options = dict(loss=loss, loss_scale=loss_scale, max_iter=max_iter, tol=tol)
    used = informative(tracks, np.ones(len(tracks.view), dtype=bool))
    if not np.all(np.isfinite(cameras.project(X, tracks.view[used], tracks.point[used]))):
        raise MpeError("the start puts points behind the cameras that see them: not a start "
                       "for these observations (try start='own')")
    fit = adjust(np.asarray(X, dtype=float), cameras, tracks.subset(used), **lm_options)
    fit, dropped = peel_outliers(fit, tracks, np.zeros(len(used), dtype=bool), outlier_threshold, lm_options)
    return _result(fit, tracks, dropped, cameras.model, max_iter, float("nan"), {}, lm_options)


def _median_of(fit, tracks, kept) -> float:
    return float(np.median(residual_lengths(*fit[:2], tracks, kept)))


def _rms_of(fit, tracks, kept) -> float:
    return float(np.sqrt(np.mean(residual_lengths(*fit[:2], tracks, kept) ** 2)))


def _epipolar_flags(tracks, threshold) -> np.ndarray:
    """(T,) bool: the likely wrong matches that two views at a time show, before
    any fit (:mod:`.epipolar`); none when wrong matches are not looked for."""
    if not np.isfinite(threshold):
        return np.zeros(len(tracks.view), dtype=bool)
    return epipolar_outliers(tracks.view, tracks.point, tracks.z, tracks.n_views,
                             tracks.n_points, floor=1e-5 * image_size(tracks))


def _say_if_the_data_disagree(camera, median):
    """One line when another camera model explains the keypoints far better."""
    better = {model: value for model, value in median.items()
              if model != camera and value < DISAGREE_RATIO * median[camera]}
    if better:
        model = min(better, key=better.get)
        warn(f"the keypoints disagree with the {camera} camera: median residual "
             f"{median[camera]:.3g} px, against {better[model]:.3g} px with the {model} camera "
             f"(camera='{model}')")


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

