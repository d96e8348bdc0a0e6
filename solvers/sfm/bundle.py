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
3. bundle adjustment of the ``scaled`` model from each start, scouted, the
   best one solved to the end; ``orthographic`` from it with one scale for
   all views, ``perspective`` from it at several focal lengths and in both
   depth orders, the one with the lowest error kept.

Wrong matches are first suspected before any fit, two views at a time
(:mod:`.epipolar`) and by the incremental start, and left out of every fit;
then peeled off against a robust residual scale (the median residual length)
and the problem solved again, until none is left (:func:`_without_outliers`);
last, the points with dropped observations are triangulated again robustly
under the final cameras, and what the fit explains is taken back
(:func:`_readmitted`). The points of weak geometry (:func:`weak_geometry`)
sit out the long solves (:func:`_peeled`) and are adjusted alone after them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.options import CAMERAS, REPROJECTION_LOSSES
from mpe3d.solvers.degenerate import warn
from mpe3d.solvers.factorize import affine_als, metric_upgrade_pd
from mpe3d.solvers.linalg import elongation, sum_by
from mpe3d.solvers.sfm import incremental
from mpe3d.solvers.sfm.adjust import Fit, adjust, one_blas_thread
from mpe3d.solvers.sfm.cameras import (
    MATRIX,
    PINHOLES,
    Cameras,
    affine_cameras,
    known_matrices,
    with_distortion,
)
from mpe3d.solvers.sfm.epipolar import epipolar_outliers
from mpe3d.solvers.sfm.tracks import EXACT, Tracks, image_size, residual_lengths, rms, robust_sigma
from mpe3d.solvers.sfm.triangulation import (
    adjusted_points,
    dlt_rows,
    least_squares_points,
    ray_directions,
    robust_points,
    widest_angles,
)
from mpe3d.solvers.stress import project_rows

# Focal lengths tried from the weak-perspective start, in units of the image size.
# (Shorter ones put the cloud behind the camera: a half-image-wide object at
# depth f / s.)
_FOCAL_STARTS = (1.0, 2.0, 4.0)
_SCOUT = 8  # iterations from each start before the best is chosen, at most
_RACE = (2, 4, _SCOUT)  # the stages of that race (iterations done after each)
_RACE_RATIO = 2.0  # a start this many times the best's RMS after a stage is dropped
# points a race is run on, at most: enough to rank starts 2x apart, and the
# race's iterations then cost what 1,000 points cost, however many there are
RACE_POINTS = 1000
START_ITERATIONS = 20  # the scaled fit's when it is only a pinhole's start
_ROUND_TOL = 1e-6  # between two rounds of dropping wrong matches
_TRANSLATION_SWEEPS = 3  # known orthographic cameras: points and image origins in turn
# A cloud longer than this many times its second extent has not been determined
# along its long axis: the views leave its depth free.
_ELONGATION = 20.0
_OUTLIER_ROUNDS = 20
_READMISSION_ROUNDS = 4
_RUNAWAY_ROUNDS = 3  # solves without the points that ran away
_PLACING_STEPS = 10  # Gauss-Newton steps that put a point seen once on its ray
# In robust sigmas: real tracks have heavy tails (0.1% of VGG's verified house
# and dino observations lie beyond 26-58 sigmas of a pinhole fit), while a
# wrong match is typically hundreds of sigmas away.
OUTLIER_THRESHOLD = 20.0
# Weak geometry: a point whose kept rays all meet under MIN_RAY_ANGLE degrees
# (COLMAP's triangulator refuses these too), or that lies farther from the
# cloud's median than FAR_FACTOR times the median distance of the cloud's
# points to it, has no depth the views fix: it is left unplaced, like a point
# seen once. On COLMAP's tracks of 250 photos one such point, its rays a
# fraction of a degree apart, stood 7e8 away and set the whole cloud's mean CD.
MIN_RAY_ANGLE = 1.5
FAR_FACTOR = 100.0
AUTO_RATIO = 0.8  # camera="auto" keeps the pinhole below this share of the weak median residual
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
    affine_rms: float  # RMS of the affine factorisation, a floor for any camera model
    camera: str = "scaled"  # the model fitted (auto resolved)
    info: dict[str, Any] = field(default_factory=dict)

    def rms(self, rows=None) -> float:
        """sqrt(mean ||r_t||^2) in pixels over ``rows``, by default the kept
        observations of the placed points (an unplaced point's depth, and so
        its residual, is a guess)."""
        return rms(self.residuals[self.counted if rows is None else rows])


# -- the start -------------------------------------------------------------------

class WeakStart(NamedTuple):
    """The weak-perspective start: points, orthonormal rows, scales, translations,
    and the RMS of the affine fit under it."""

    X: np.ndarray
    P: np.ndarray  # (K, 2, 3)
    scale: np.ndarray  # (K,)
    t: np.ndarray  # (K, 2)
    affine_rms: float


def weak_perspective_start(tracks: Tracks, sweeps: int = 20, tol: float = 1e-10) -> WeakStart:
    """X, orthonormal rows P (K, 2, 3), scales s and translations t from the
    affine factorisation (``sweeps`` alternating sweeps after it is grown) and
    the positive-definite upgrade, and the RMS of the affine fit."""
    X, L, _, _ = affine_als(tracks.view, tracks.point, tracks.z, tracks.n_points,
                            tracks.n_views, sweeps, tol)
    t = _translations(X, L, tracks)
    affine = np.einsum("tab,ta->tb", L[tracks.view], X[tracks.point]) + t[tracks.view] - tracks.z
    A = metric_upgrade_pd(L)
    X = X @ np.linalg.inv(A).T
    rows = np.einsum("ia,kib->kba", A, L)  # (K, 2, 3): s_k times orthonormal rows
    scale = np.sqrt(np.sum(rows ** 2, axis=(1, 2)) / 2)
    norm = np.exp(np.mean(np.log(scale)))  # the cloud in pixels at the mean scale
    X, scale = X * norm, scale / norm
    X = X - X.mean(axis=0)
    P = project_rows(rows)
    t = _translations_for(X, P, scale, tracks)
    return WeakStart(X, P, scale, t, rms(affine))


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
        ``AUTO_RATIO`` times the weak perspective's). "radial" is the pinhole
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
    flagged = epipolar_flags(tracks, outlier_threshold)
    used = _informative(tracks, ~flagged)
    grown = incremental.incremental_start(tracks.subset(used), _finite(outlier_threshold))
    if grown is not None and np.isfinite(outlier_threshold):  # its left-outs are suspects too
        flagged[np.flatnonzero(used)[grown.left_out]] = True
        used = _informative(tracks, ~flagged)
    # a pinhole asked for: the scaled fit is its start, which needs no more than
    # START_ITERATIONS (the weak perspective of pinhole photos converges slowly:
    # COLMAP's 250-photo spiral ran to 100 iterations, 12 s, for the same pinhole)
    start_options = lm_options if camera in ("auto", "orthographic", "scaled") \
        else {**lm_options, "max_iter": min(lm_options["max_iter"], START_ITERATIONS)}
    fit, affine_rms = _scaled(tracks.subset(used), start_options,
                              None if grown is None else grown[:2])  # (X, cameras)
    # The models are compared on the same observations, before any is dropped:
    # a weak-perspective misfit of perspective data is no wrong match.
    fits = {"scaled": fit}
    exact = _rms_of(fit, tracks, used) <= 1e3 * EXACT * image_size(tracks)
    if exact and camera == "auto":  # orthographic views, noise-free: nothing fits better
        camera = "scaled"
    wanted = ("scaled", "perspective") if camera == "auto" else (camera,)
    others = {"orthographic": ("scaled", "perspective"), "scaled": ("perspective",),
              "perspective": ("scaled",), "radial": ("scaled",)}
    # the radial camera starts from the pinhole's fit, so that one comes first
    needed = ("perspective",) if camera == "radial" else ()
    for model in dict.fromkeys(needed + wanted + ((), others.get(camera, ()))[not exact]):
        if model not in fits:
            fits[model] = _FITTERS[model](*(fits["perspective"] if model == "radial" else fit)[:2],
                                          tracks.subset(used), principal_point, shared_focal,
                                          lm_options)
            fits[model], runaways = _without_runaways(fits[model], tracks, used, lm_options)
            flagged |= runaways  # suspects, as the two-view test's are
    rms = {model: _rms_of(f, tracks, used) for model, f in fits.items()}
    # the models are judged by their median residual, which wrong matches do not sway
    median = {model: _median_of(f, tracks, used) for model, f in fits.items()}
    if not np.isfinite(rms[camera if camera != "auto" else "scaled"]):
        raise MpeError("the keypoints do not determine a 3D shape: no start gives finite "
                       "cameras (a planar scene, or too few points shared by the views?)")
    if camera == "auto":
        camera = "perspective" if median["perspective"] < AUTO_RATIO * median["scaled"] \
            else "scaled"
    _say_if_the_data_disagree(camera, median)
    fit, dropped = _peeled(fits[camera], tracks, flagged, outlier_threshold, lm_options)
    return _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, lm_options)


def _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, lm_options) -> BundleResult:
    """The result of a fit: weak points out of it, points seen once placed on
    their rays, every residual."""
    fit, placed, narrow, far = _without_weak(fit, tracks, dropped, lm_options)
    X, cameras, history, converged = fit
    # a narrow point keeps the adjustment's depth (its best guess, and its rays'
    # fit); a far one has none worth keeping: it goes to the cloud's depth
    X = _place_unplaced(X, cameras, tracks, placed & ~far, ~dropped)
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
                              "weak": weak})


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
    weak, placed, narrow, far = _weak_points(fit, tracks, ~dropped)
    if not weak.any():
        return fit, placed, narrow, far
    strong = _informative(tracks, ~dropped & ~weak[tracks.point])
    again = adjust(*fit[:2], tracks.subset(strong), **lm_options)
    return again._replace(history=np.concatenate([fit.history, again.history[1:]])), placed, narrow, far


def weak_geometry(X, cameras: Cameras, tracks: Tracks, kept: np.ndarray,
                  placed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (N,) bool masks of the ``placed`` points whose depth the views do
    not fix: ``narrow``, their ``kept`` rays all meet under ``MIN_RAY_ANGLE``
    degrees; ``far``, they lie farther from the cloud's median than
    ``FAR_FACTOR`` times the median distance of the placed points to it."""
    if not placed.any():
        return placed.copy(), placed.copy()
    rows = kept & placed[tracks.point]
    rays, lines = ray_directions(cameras.projection_matrices(), X, tracks.view[rows],
                                 tracks.point[rows])
    narrow = widest_angles(rays, tracks.point[rows], tracks.n_points, lines) < MIN_RAY_ANGLE
    far = ~(median_radii(X, placed) <= FAR_FACTOR)  # a nan is far too
    return placed & narrow, placed & far


def median_radii(X: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """(N,) each point's distance from the median of the points ``among``, in
    median distances of those points to it: the unit of ``FAR_FACTOR``."""
    among = np.ones(len(X), dtype=bool) if among is None else among
    distance = np.linalg.norm(X - np.median(X[among], axis=0), axis=1)
    return distance / max(float(np.median(distance[among])), 1e-300)


def _say_if_depth_is_free(X, placed, weak, camera) -> None:
    """One line when the views fix the depth of too few points, or of none
    but a cloud far longer than wide: their baseline is too small."""
    fixed = placed & ~weak
    if placed.sum() <= 3:
        return
    if weak.sum() > placed.sum() / 2:
        why = (f"{int(weak.sum())} of {int(placed.sum())} points' rays meet under "
               f"{MIN_RAY_ANGLE:g} degrees, left unplaced")
    elif fixed.sum() > 3 and elongation(X[fixed]) > _ELONGATION:
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
    used = _informative(tracks, np.ones(len(tracks.view), dtype=bool))
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
            cameras.params[:, 3:5] = _mean_by_view(residual, sub)
    if cameras.model == MATRIX:
        X = least_squares_points(A, b, sub.point, sub.n_points)
    fit = adjust(X, cameras, sub, **lm_options, frozen=frozen)
    fit, dropped = _without_outliers(fit, tracks, np.zeros(len(used), dtype=bool),
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
    used = _informative(tracks, np.ones(len(tracks.view), dtype=bool))
    if not np.all(np.isfinite(cameras.project(X, tracks.view[used], tracks.point[used]))):
        raise MpeError("the start puts points behind the cameras that see them: not a start "
                       "for these observations (try start='own')")
    fit = adjust(np.asarray(X, dtype=float), cameras, tracks.subset(used), **lm_options)
    fit, dropped = _peeled(fit, tracks, np.zeros(len(used), dtype=bool), outlier_threshold, lm_options)
    return _result(fit, tracks, dropped, cameras.model, max_iter, float("nan"), {}, lm_options)


def _scaled(tracks, lm_options, grown=None):
    """The scaled fit from two affine starts, barely polished and after some
    sweeps, and from the ``grown`` (X, cameras) of :mod:`.incremental`. Which
    one reaches the lowest minimum depends on the tracks, so each is scouted
    for a few iterations and the best one solved to the end."""
    starts = []
    for sweeps in (1, 20):
        X, P, scale, t, affine_rms = weak_perspective_start(tracks, sweeps, lm_options["tol"])
        starts.append(((X, affine_cameras("scaled", P, scale, t)), affine_rms))
    if grown is not None:
        starts.append((grown, affine_rms))
    return _best_of(starts, tracks, lm_options)


def _best_of(starts, tracks, lm_options):
    """Scout the ((X, cameras), extra) starts in a race, then solve the lowest
    to the end; returns its :class:`~.adjust.Fit` and its extra.

    Each start runs to the iteration counts of ``_RACE`` in turn; after each
    stage the starts whose RMS exceeds ``_RACE_RATIO`` times the best's are
    dropped, and the race ends when one is left (or at ``_SCOUT`` iterations).
    A start that far behind after two iterations has not won on any tracks we
    have (the mirror images of a pinhole start sit 4-7x above after two), and
    every iteration here costs a full reduced camera system: the six pinhole
    starts' 48 scouting iterations were 17 s of 55 on 250 cameras x 3,000
    points. Scouts stop at a relative decrease of ``_ROUND_TOL``: the race
    only ranks them. Over ``RACE_POINTS`` placed points the race runs on
    that many of them, evenly spread (:func:`race_points`), and the others are
    placed for the winner's cameras before its solve on all: a 2x lead shows
    on 1,000 points as on 3,000, at a third of the cost an iteration (250
    cameras x 3,000 points: 37 -> 31 s, the same final RMS to 15 digits).
    """
    scout = {**lm_options, "tol": max(lm_options["tol"], _ROUND_TOL)}
    racing = [(Fit(*start, np.empty(0), False), extra) for start, extra in starts]
    raced = race_points(tracks)
    race_tracks = tracks if raced is None else tracks.subset(raced[tracks.point])
    done = 0
    for stage in _RACE:
        budget = min(stage, lm_options["max_iter"]) - done
        if budget <= 0:
            break
        racing = [(_continued(fit, race_tracks, {**scout, "max_iter": budget}), extra)
                  for fit, extra in racing]
        done += budget
        best = min(fit.history[-1] for fit, _ in racing)
        racing = [(fit, extra) for fit, extra in racing if fit.history[-1] <= _RACE_RATIO * best]
        if len(racing) == 1:
            break
    scouting, extra = min(racing, key=lambda f: f[0].history[-1])
    if raced is not None and len(scouting.history) > 1:  # cameras moved: the points left
        # out of the race placed for the cameras it reached
        scouting = scouting._replace(X=adjusted_points(scouting.X, scouting.cameras, tracks,
                                                       _placed(tracks, slice(None)) & ~raced))
    # the winner solved to the end without its points of weak geometry (see _peeled)
    weak = _weak_points(scouting, tracks, np.ones(len(tracks.view), dtype=bool))[0]
    fit = _continued(scouting._replace(converged=False), tracks.subset(~weak[tracks.point]), lm_options)
    if weak.any():
        fit = fit._replace(X=adjusted_points(fit.X, fit.cameras, tracks, weak))
    return fit, extra


def race_points(tracks) -> np.ndarray | None:
    """(N,) bool: the placed points a race of starts is run on, RACE_POINTS
    of them evenly spread over the point indices; None when there are no more
    than that (the race runs on all)."""
    ids = np.flatnonzero(_placed(tracks, slice(None)))
    if len(ids) <= RACE_POINTS:
        return None
    raced = np.zeros(tracks.n_points, dtype=bool)
    raced[ids[np.linspace(0, len(ids) - 1, RACE_POINTS).round().astype(int)]] = True
    return raced


def _continued(fit, tracks, lm_options):
    """``fit`` solved on from where it stands (unless it converged), its history kept."""
    if fit.converged:
        return fit
    more = adjust(fit.X, fit.cameras, tracks, **lm_options)
    return more._replace(history=np.concatenate([fit.history, more.history[1:] if len(fit.history)
                                                 else more.history]))


def _without_runaways(fit, tracks, used, lm_options):
    """A solve that did not converge because points ran away (a wrong match
    along its epipolar line, in a track of two views, puts its point at a
    depth the pinhole chases towards infinity, and the shared damping holds
    back every other parameter): solved again without the points beyond
    ``FAR_FACTOR`` median radii, until none is left. Returns the fit and the
    observations of the points left out, for the caller's suspects."""
    out = np.zeros(len(tracks.view), dtype=bool)
    for _ in range(_RUNAWAY_ROUNDS):
        if fit.converged:
            break
        placed = _placed(tracks, used & ~out)
        far = placed & ~(median_radii(fit.X, placed) <= FAR_FACTOR)
        if not far.any() or far.sum() > placed.sum() / 2:
            break
        out |= far[tracks.point] & used
        again = adjust(fit.X, fit.cameras, tracks.subset(_informative(tracks, used & ~out)), **lm_options)
        fit = again._replace(history=np.concatenate([fit.history, again.history[1:]]))
    return fit, out


def _informative(tracks: Tracks, kept: np.ndarray) -> np.ndarray:
    """The observations ``kept`` less those of points kept in fewer than 2 views: a point
    seen once fits any camera, so it says nothing about them (it is placed on
    its ray afterwards)."""
    counts = np.bincount(tracks.point[kept], minlength=tracks.n_points)
    return kept & (counts[tracks.point] >= 2)


def _placed(tracks, used) -> np.ndarray:
    """(N,) bool: the points the solve placed (seen in 2 or more views)."""
    return np.bincount(tracks.point[used], minlength=tracks.n_points) >= 2


def _median_of(fit, tracks, kept) -> float:
    return float(np.median(residual_lengths(*fit[:2], tracks, kept)))


def _rms_of(fit, tracks, kept) -> float:
    return float(np.sqrt(np.mean(residual_lengths(*fit[:2], tracks, kept) ** 2)))


def epipolar_flags(tracks, threshold) -> np.ndarray:
    """(T,) bool: the likely wrong matches that two views at a time show, before
    any fit (:mod:`.epipolar`); none when wrong matches are not looked for."""
    if not np.isfinite(threshold):
        return np.zeros(len(tracks.view), dtype=bool)
    return epipolar_outliers(tracks.view, tracks.point, tracks.z, tracks.n_views,
                             tracks.n_points, floor=1e-5 * image_size(tracks))


def _readmitted(fit, tracks, dropped, threshold, lm_options):
    """The fit after every point with dropped observations is triangulated again,
    robustly, under its cameras (:func:`.triangulation.robust_points`), and
    solved again with the observations it explains (within ``threshold``
    robust sigmas) taken back and those it does not dropped, until that
    changes nothing: a suspicion raised before the fit, or a drop made while a
    wrong match still dragged its point, is not the final word."""
    if not np.isfinite(threshold):
        return fit, dropped
    for _ in range(_READMISSION_ROUNDS):
        X, cameras = fit[:2]
        tau = threshold * robust_sigma(X, cameras, tracks, _informative(tracks, ~dropped))
        suspects = np.unique(tracks.point[dropped])
        X, outlying = robust_points(X, cameras, tracks, suspects, tau)
        again = np.where(np.isin(tracks.point, suspects), outlying, dropped)
        if (again == dropped).all():
            break
        fit = adjust(X, cameras, tracks.subset(_informative(tracks, ~again)), **lm_options)
        fit, dropped = _without_outliers(fit, tracks, again, threshold, lm_options)
    return fit, dropped


def _finite(threshold):
    return threshold if np.isfinite(threshold) else OUTLIER_THRESHOLD


def _weak_points(fit, tracks, kept):
    """(N,) bool masks ``weak``, ``placed``, ``narrow`` and ``far``: the points
    of weak geometry (:func:`weak_geometry`) under ``fit`` with the ``kept``
    observations, and what they are made of. ``weak`` is none when they are
    over half the placed points: then no depth is fixed, which is said, not
    solved."""
    placed = _placed(tracks, _informative(tracks, kept))
    narrow, far = weak_geometry(*fit[:2], tracks, kept, placed)
    weak = narrow | far
    return (weak if weak.sum() <= placed.sum() / 2 else np.zeros_like(weak)), placed, narrow, far


def _peeled(fit, tracks, flagged, threshold, lm_options):
    """The fit and the observations dropped after wrong matches are peeled off
    (:func:`_without_outliers`) and what the fit explains is taken back
    (:func:`_readmitted`), with the points of weak geometry under ``fit`` set
    aside: :func:`_without_weak` leaves them out of the last solve anyway,
    and their depth, which the views barely fix, is what every solve with
    them spends its last iterations on (COLMAP's tracks of 250 photos: 14
    such points; the peeling's 21 solves took 156 iterations with them, 21
    without). They are then adjusted alone under the cameras found
    (:func:`.triangulation.adjusted_points`), as the solves would have
    placed them. Their observations flagged before stay dropped."""
    weak = _weak_points(fit, tracks, ~flagged)[0]
    rows = ~weak[tracks.point]
    strong = tracks.subset(rows)
    fit, peeled = _without_outliers(fit, strong, flagged[rows], threshold, lm_options)
    fit, peeled = _readmitted(fit, strong, peeled, threshold, lm_options)
    dropped = flagged.copy()
    dropped[rows] = peeled
    if weak.any():
        fit = fit._replace(X=adjusted_points(fit.X, fit.cameras, tracks.subset(~dropped), weak))
    return fit, dropped


def _without_outliers(fit, tracks, dropped, threshold, lm_options):
    """Find wrong matches, drop them and solve again, until none is left.

    Peeling: the observations beyond ``threshold`` robust sigmas (from the
    median residual length) are dropped, at most one per point and one per
    view and round, the worst (a wrong match drags its point and its camera,
    and so their other residuals, with it), and only where the point keeps 3
    views, so that it stays placed and testable. As the fit sheds them the
    sigma shrinks and subtler ones show. A view keeps at least 6 observations.
    """
    if not np.isfinite(threshold):
        return fit, dropped
    before = dropped
    for _ in range(_OUTLIER_ROUNDS):
        kept = _informative(tracks, ~dropped)
        X, cameras = fit[:2]
        sigma = robust_sigma(X, cameras, tracks, kept)
        length = np.where(kept, np.nan_to_num(residual_lengths(X, cameras, tracks), nan=np.inf), -1.0)
        ranked = np.argsort(length)
        worst = np.intersect1d(_last_of(tracks.point[ranked], ranked),  # the worst of its point
                               _last_of(tracks.view[ranked], ranked))  # and of its view
        counts = np.bincount(tracks.point[kept], minlength=tracks.n_points)
        worst = worst[(length[worst] > threshold * sigma) & (counts[tracks.point[worst]] >= 4)]
        bad = np.zeros(len(tracks.view), dtype=bool)
        bad[worst] = True
        room = np.bincount(tracks.view[~dropped & ~bad], minlength=tracks.n_views) >= 6
        bad &= room[tracks.view]
        if not bad.any():
            break
        dropped = dropped | bad
        fit = adjust(X, cameras, tracks.subset(_informative(tracks, ~dropped)),
                     **{**lm_options, "tol": max(lm_options["tol"], _ROUND_TOL)})
    if (dropped != before).any():  # the rounds solve loosely: the last one to the end
        fit = adjust(*fit[:2], tracks.subset(_informative(tracks, ~dropped)), **lm_options)
    return fit, dropped


def _last_of(groups: np.ndarray, items: np.ndarray) -> np.ndarray:
    """The last item of each group, in the order given."""
    _, first = np.unique(groups[::-1], return_index=True)
    return np.sort(items[::-1][first])


def _say_if_the_data_disagree(camera, median):
    """One line when another camera model explains the keypoints far better."""
    better = {model: value for model, value in median.items()
              if model != camera and value < DISAGREE_RATIO * median[camera]}
    if better:
        model = min(better, key=better.get)
        warn(f"the keypoints disagree with the {camera} camera: median residual "
             f"{median[camera]:.3g} px, against {better[model]:.3g} px with the {model} camera "
             f"(camera='{model}')")


def _place_unplaced(X, cameras, tracks, placed, kept):
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
        if not np.all(np.isfinite(r)) or np.abs(r).max() <= EXACT * image_size(tracks):
            break
        d_x = cameras.jacobian_blocks(X, view, point)[0]
        step = np.einsum("tij,tj->ti", np.linalg.pinv(d_x), -r)
        X += sum_by(point, step, tracks.n_points) / counts[:, None]
    return X


def _orthographic(X, scaled: Cameras, tracks, principal_point, shared_focal, lm_options):
    """From the scaled solution: one scale for all views, folded into the cloud."""
    s = scaled.scale()
    common = float(np.exp(np.mean(np.log(s))))
    R = scaled.current_rotations()
    start = affine_cameras("orthographic", R[:, :2], np.ones(len(s)), scaled.params[:, 3:5])
    return adjust(X * common, start, tracks, **lm_options)


def _perspective(X, scaled: Cameras, tracks, principal_point, shared_focal, lm_options):
    """From the scaled solution, at several focal lengths and in both depth
    orders (weak perspective cannot tell a cloud from its mirror image in depth;
    a pinhole can): a short solve from each, then the best one to the end."""
    z = tracks.z
    c = (z.min(axis=0) + z.max(axis=0)) / 2 if principal_point is None \
        else np.asarray(principal_point, dtype=float)
    size = image_size(tracks)
    R, s, t = scaled.current_rotations(), scaled.scale(), scaled.params[:, 3:5]
    centre = X.mean(axis=0)  # the pinhole matches the weak perspective at the centroid
    X, t = X - centre, t + s[:, None] * (R[:, :2] @ centre)
    X = _bounded_depth(X)
    starts = []
    for mirror in (1.0, -1.0):  # -X seen through -R[:2] gives the same weak-perspective images
        for factor in _FOCAL_STARTS:
            cameras = affine_cameras("perspective", mirror * R[:, :2], s, t, focal=factor * size,
                                     principal_point=c, shared_focal=shared_focal)
            starts.append(((in_front(mirror * X, cameras, tracks), cameras), None))
    return _best_of(starts, tracks, lm_options)[0]


def _radial(X, pinhole: Cameras, tracks, principal_point, shared_focal, lm_options):
    """From the pinhole's solution, with k1 = k2 = 0: a lens's distortion is a
    small change of a pinhole's images, so its optimum is near."""
    return adjust(X, with_distortion(pinhole), tracks, **lm_options)


_FITTERS = {"orthographic": _orthographic, "perspective": _perspective, "radial": _radial}


def in_front(X: np.ndarray, cameras: Cameras, tracks: Tracks, keep: float = 0.5) -> np.ndarray:
    """X with each point that some view of it would see behind its pinhole pulled
    towards the centroid (which every camera sees at depth f / s) until it stands
    at ``keep`` times that depth or more: one such point would make the whole
    start's cost infinite. Long sequences round an object (COLMAP's tracks of
    250 photos) hold a few two-view points far out in depth."""
    R = cameras.current_rotations()
    toward = np.einsum("ti,ti->t", R[tracks.view, 2], X[tracks.point])  # X is centred
    depth = cameras.params[tracks.view, 5]
    behind = toward < (keep - 1.0) * depth  # depth + toward < keep * depth
    if not behind.any():
        return X
    alpha = np.ones(len(X))
    np.minimum.at(alpha, tracks.point[behind], (1.0 - keep) * depth[behind] / -toward[behind])
    return X * alpha[:, None]


def _bounded_depth(X: np.ndarray, limit: float = _ELONGATION) -> np.ndarray:
    """X with a run-away principal axis pulled in to the second one's extent: a
    start from which no point lies behind a pinhole camera."""
    if elongation(X) <= limit:
        return X
    centred = X - X.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]
    coords = centred @ axes.T
    extents = np.ptp(coords, axis=0)
    coords[:, 0] *= extents[1] / extents[0]
    return coords @ axes + X.mean(axis=0)


def _translations(X, L, tracks):
    """The per-view 2D translations that best fit z_t ~ L_k^T x_i + t_k."""
    pred = np.einsum("tab,ta->tb", L[tracks.view], X[tracks.point])
    return _mean_by_view(tracks.z - pred, tracks)


def _translations_for(X, P, scale, tracks):
    pred = scale[tracks.view, None] * np.einsum("tab,tb->ta", P[tracks.view], X[tracks.point])
    return _mean_by_view(tracks.z - pred, tracks)


def _mean_by_view(values, tracks):
    counts = np.maximum(np.bincount(tracks.view, minlength=tracks.n_views), 1)
    return sum_by(tracks.view, values, tracks.n_views) / counts[:, None]


# -- bundle adjustment -----------------------------------------------------------


