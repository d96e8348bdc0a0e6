"""Keypoints: minimise the reprojection error over the 3D points and the cameras.

When views come as 2D coordinates (matched keypoints, in pixels), the problem
they pose is bundle adjustment, not the distance stress of paper Eq. 1:

    E(X, C) = sum_t rho(||u_k(x_i; C_k) - z_t||^2)

over the observations t = (view k, point i, 2D point z_t), for a camera model
u (:mod:`mpe3d.solvers.cameras`) with analytic Jacobians. It is solved by
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
(:func:`_readmitted`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import csr_matrix
from threadpoolctl import threadpool_limits

from mpe3d.errors import MpeError

from .base import Observations
from . import incremental
from .cameras import CAMERAS, MATRIX, Cameras, affine_cameras, known_matrices
from .degenerate import warn
from .epipolar import epipolar_outliers
from .factorize import _stacked, _sum_by, affine_als, metric_upgrade_pd
from .linalg import elongation
from .stress import project_rows
from .triangulation import (dlt_rows, least_squares_points, ray_directions, robust_points,
                            widest_angles)

LOSSES = ("l2", "huber", "soft_l1", "cauchy")
# Focal lengths tried from the weak-perspective start, in units of the image size.
# (Shorter ones put the cloud behind the camera: a half-image-wide object at
# depth f / s.)
_FOCAL_STARTS = (1.0, 2.0, 4.0)
_SCOUT = 8  # iterations from each start before the best is chosen
_ROUND_TOL = 1e-6  # between two rounds of dropping wrong matches
_EXACT = 1e-12  # an RMS below this share of the image is exact: no model can do better
_TRANSLATION_SWEEPS = 3  # known orthographic cameras: points and image origins in turn
# A cloud longer than this many times its second extent has not been determined
# along its long axis: the views leave its depth free.
_ELONGATION = 20.0
_OUTLIER_ROUNDS = 20
_READMISSION_ROUNDS = 4
_PLACING_STEPS = 10  # Gauss-Newton steps that put a point seen once on its ray
_DENSE_Y = 4_000_000  # entries of the Schur factor Y below which it is made dense
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
# Rayleigh: the median of ||r|| for isotropic Gaussian 2D residuals of std sigma.
_RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))
AUTO_RATIO = 0.8  # camera="auto" keeps the pinhole below this share of the weak median residual
DISAGREE_RATIO = 0.5  # another model this much better is said


@dataclass
class Tracks:
    """Every observation as flat arrays: its view, its point and its 2D point (pixels)."""

    view: np.ndarray  # (T,)
    point: np.ndarray  # (T,)
    z: np.ndarray  # (T, 2)
    n_points: int
    n_views: int

    @classmethod
    def from_observations(cls, obs: Observations) -> "Tracks":
        if any(v.coordinates is None for v in obs.views):
            raise MpeError("the reprojection objective needs 2D coordinates in every view "
                           "(distance matrices only allow objective='stress')")
        view, point, z = _stacked(obs, [v.coordinates for v in obs.views])
        return cls(view, point, np.asarray(z, dtype=float), obs.n_points, obs.n_views)

    def subset(self, rows: np.ndarray) -> "Tracks":
        return Tracks(self.view[rows], self.point[rows], self.z[rows], self.n_points, self.n_views)


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
        return _rms(self.residuals[self.counted if rows is None else rows])


# -- the start -------------------------------------------------------------------

def weak_perspective_start(tracks: Tracks, sweeps: int = 20, tol: float = 1e-10):
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
    return X, P, scale, t, _rms(affine)


def _one_blas_thread(func):
    """Run ``func`` on one BLAS thread: its matrices are small (3x3 blocks, a
    K*6 camera system), where threads cost more than they give (backyard, 100
    views: 2.8 s on one thread, 5.4 s on two)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(1):
            return func(*args, **kwargs)
    return wrapper


@_one_blas_thread
def bundle_adjust(tracks: Tracks, camera: str = "auto", *, principal_point=None,
                  shared_focal: bool = True, loss: str = "l2", loss_scale: float = 1.0,
                  outlier_threshold: float = OUTLIER_THRESHOLD, max_iter: int = 100,
                  tol: float = 1e-10) -> BundleResult:
    """Points and cameras of model ``camera`` that minimise the reprojection error.

    Parameters
    ----------
    tracks : Tracks
        The observations, in pixels.
    camera : {"auto", "orthographic", "scaled", "perspective"}, default "auto"
        "auto" fits ``scaled`` and ``perspective`` and keeps the pinhole camera
        when it explains the keypoints clearly better (median residual below
        ``AUTO_RATIO`` times the weak perspective's).
    principal_point : (2,) or None, default None
        Perspective only; None takes the centre of the keypoints' bounding box.
    shared_focal : bool, default True
        Perspective only: one focal length for all views, or one per view.
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
    if camera not in ("auto",) + CAMERAS:
        raise MpeError(f"camera: expected one of auto, {', '.join(CAMERAS)}, got {camera!r}")
    if loss not in LOSSES:
        raise MpeError(f"loss: expected one of {', '.join(LOSSES)}, got {loss!r}")
    solve = dict(loss=loss, loss_scale=loss_scale, max_iter=max_iter, tol=tol)
    flagged = _epipolar_flags(tracks, outlier_threshold)
    used = _informative(tracks, ~flagged)
    grown = incremental.incremental_start(tracks.subset(used), _finite(outlier_threshold))
    if grown is not None and np.isfinite(outlier_threshold):  # its left-outs are suspects too
        flagged[np.flatnonzero(used)[grown[2]]] = True
        used = _informative(tracks, ~flagged)
    fit, affine_rms = _scaled(tracks.subset(used), solve, None if grown is None else grown[:2])
    # The models are compared on the same observations, before any is dropped:
    # a weak-perspective misfit of perspective data is no wrong match.
    fits = {"scaled": fit}
    exact = _rms_of(fit, tracks, used) <= 1e3 * _EXACT * _image_size(tracks)
    if exact and camera == "auto":  # orthographic views, noise-free: nothing fits better
        camera = "scaled"
    wanted = ("scaled", "perspective") if camera == "auto" else (camera,)
    others = {"orthographic": ("scaled", "perspective"), "scaled": ("perspective",),
              "perspective": ("scaled",)}
    for model in dict.fromkeys(wanted + ((), others.get(camera, ()))[not exact]):  # + checks
        if model not in fits:
            fits[model] = (_orthographic if model == "orthographic" else _perspective)(
                *fit[:2], tracks.subset(used), principal_point, shared_focal, solve)
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
    fit, dropped = _without_outliers(fits[camera], tracks, flagged, outlier_threshold, solve)
    fit, dropped = _readmitted(fit, tracks, dropped, outlier_threshold, solve)
    return _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, solve)


def _result(fit, tracks, dropped, camera, max_iter, affine_rms, rms, solve) -> BundleResult:
    """The result of a fit: weak points out of it, points seen once placed on
    their rays, every residual."""
    fit, placed, narrow, far = _without_weak(fit, tracks, dropped, solve)
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


def _without_weak(fit, tracks, dropped, solve):
    """The fit solved again without the points of weak geometry, as COLMAP
    filters its points before its last adjustment: their rays, nearly
    parallel, pull on the cameras for no depth (a point 7e8 away among COLMAP's
    250 photos). Returns the fit, the points placed before, and the ``narrow``
    and ``far`` masks."""
    X, cameras = fit[:2]
    placed = _placed(tracks, _informative(tracks, ~dropped))
    narrow, far = weak_geometry(X, cameras, tracks, ~dropped, placed)
    weak = narrow | far
    if not weak.any() or weak.sum() > placed.sum() / 2:  # then no depth is fixed: said, not solved
        return fit, placed, narrow, far
    strong = _informative(tracks, ~dropped & ~weak[tracks.point])
    X, cameras, history, converged = adjust(X, cameras, tracks.subset(strong), **solve)
    return (X, cameras, np.concatenate([fit[2], history[1:]]), converged), placed, narrow, far


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
         + ("" if camera == "perspective" else "; try camera='perspective'"))


@_one_blas_thread
def known_cameras(tracks: Tracks, matrices: np.ndarray, *, loss: str = "l2",
                  loss_scale: float = 1.0, outlier_threshold: float = OUTLIER_THRESHOLD,
                  max_iter: int = 100, tol: float = 1e-10) -> BundleResult:
    """The points (and each view's 2D translation) for known cameras: (K, 2, 3)
    orthonormal rows, an orthographic camera whose image origin is free, or
    (K, 3, 4) pinhole matrices, which fix everything but the points."""
    if loss not in LOSSES:
        raise MpeError(f"loss: expected one of {', '.join(LOSSES)}, got {loss!r}")
    solve = dict(loss=loss, loss_scale=loss_scale, max_iter=max_iter, tol=tol)
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
    fit = adjust(X, cameras, sub, **solve, frozen=frozen)
    fit, dropped = _without_outliers(fit, tracks, np.zeros(len(used), dtype=bool),
                                     outlier_threshold, {**solve, "frozen": frozen})
    return _result(fit, tracks, dropped, cameras.model if cameras.model == MATRIX
                   else "orthographic", max_iter, float("nan"), {}, {**solve, "frozen": frozen})


def _scaled(tracks, solve, grown=None):
    """The scaled fit from two affine starts, barely polished and after some
    sweeps, and from the ``grown`` (X, cameras) of :mod:`.incremental`. Which
    one reaches the lowest minimum depends on the tracks, so each is scouted
    for a few iterations and the best one solved to the end."""
    starts = []
    for sweeps in (1, 20):
        X, P, scale, t, affine_rms = weak_perspective_start(tracks, sweeps, solve["tol"])
        starts.append(((X, affine_cameras("scaled", P, scale, t)), affine_rms))
    if grown is not None:
        starts.append((grown, affine_rms))
    return _best_of(starts, tracks, solve)


def _best_of(starts, tracks, solve):
    """Scout each ((X, cameras), extra) start for a few iterations, then solve
    the lowest to the end; returns (X, cameras, history, converged) and its extra."""
    scout = {**solve, "max_iter": min(_SCOUT, solve["max_iter"])}
    scouted = [(adjust(*start, tracks, **scout), extra)
               for start, extra in starts]
    (X, cameras, scouting, _), extra = min(scouted, key=lambda f: f[0][2][-1])
    X, cameras, history, converged = adjust(X, cameras, tracks, **solve)
    return (X, cameras, np.concatenate([scouting, history[1:]]), converged), extra


def _informative(tracks: Tracks, kept: np.ndarray) -> np.ndarray:
    """The observations ``kept`` less those of points kept in fewer than 2 views: a point
    seen once fits any camera, so it says nothing about them (it is placed on
    its ray afterwards)."""
    counts = np.bincount(tracks.point[kept], minlength=tracks.n_points)
    return kept & (counts[tracks.point] >= 2)


def _placed(tracks, used) -> np.ndarray:
    """(N,) bool: the points the solve placed (seen in 2 or more views)."""
    return np.bincount(tracks.point[used], minlength=tracks.n_points) >= 2


def _lengths(X, cameras, tracks, rows=slice(None)) -> np.ndarray:
    """||u_t - z_t|| for the observations ``rows``."""
    r = cameras.project(X, tracks.view[rows], tracks.point[rows]) - tracks.z[rows]
    return np.linalg.norm(r, axis=1)


def _median_of(fit, tracks, kept) -> float:
    return float(np.median(_lengths(*fit[:2], tracks, kept)))


def _rms_of(fit, tracks, kept) -> float:
    return float(np.sqrt(np.mean(_lengths(*fit[:2], tracks, kept) ** 2)))


def _epipolar_flags(tracks, threshold) -> np.ndarray:
    """(T,) bool: the likely wrong matches that two views at a time show, before
    any fit (:mod:`.epipolar`); none when wrong matches are not looked for."""
    if not np.isfinite(threshold):
        return np.zeros(len(tracks.view), dtype=bool)
    return epipolar_outliers(tracks.view, tracks.point, tracks.z, tracks.n_views,
                             tracks.n_points, floor=1e-5 * _image_size(tracks))


def _readmitted(fit, tracks, dropped, threshold, solve):
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
        tau = threshold * _sigma(X, cameras, tracks, _informative(tracks, ~dropped))
        suspects = np.unique(tracks.point[dropped])
        X, outlying = robust_points(X, cameras, tracks, suspects, tau)
        again = np.where(np.isin(tracks.point, suspects), outlying, dropped)
        if (again == dropped).all():
            break
        fit = adjust(X, cameras, tracks.subset(_informative(tracks, ~again)), **solve)
        fit, dropped = _without_outliers(fit, tracks, again, threshold, solve)
    return fit, dropped


def _finite(threshold):
    return threshold if np.isfinite(threshold) else OUTLIER_THRESHOLD


def _without_outliers(fit, tracks, dropped, threshold, solve):
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
        sigma = _sigma(X, cameras, tracks, kept)
        length = np.where(kept, np.nan_to_num(_lengths(X, cameras, tracks), nan=np.inf), -1.0)
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
                     **{**solve, "tol": max(solve["tol"], _ROUND_TOL)})
    if (dropped != before).any():  # the rounds solve loosely: the last one to the end
        fit = adjust(*fit[:2], tracks.subset(_informative(tracks, ~dropped)), **solve)
    return fit, dropped


def _last_of(groups: np.ndarray, items: np.ndarray) -> np.ndarray:
    """The last item of each group, in the order given."""
    _, first = np.unique(groups[::-1], return_index=True)
    return np.sort(items[::-1][first])


def _sigma(X, cameras, tracks, kept) -> float:
    length = _lengths(X, cameras, tracks, kept)
    # floored: keypoints are never better than 1e-5 of the image, and exact data solved
    # loosely between rounds must not make its last digits look like wrong matches
    return max(float(np.median(length)) / _RAYLEIGH_MEDIAN, 1e-5 * _image_size(tracks))


def _image_size(tracks) -> float:
    return float(np.max(np.ptp(tracks.z, axis=0))) or 1.0


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
        if not np.all(np.isfinite(r)) or np.abs(r).max() <= _EXACT * _image_size(tracks):
            break
        d_x = cameras.jacobian_blocks(X, view, point)[0]
        step = np.einsum("tij,tj->ti", np.linalg.pinv(d_x), -r)
        X += _sum_by(point, step, tracks.n_points) / counts[:, None]
    return X


def _orthographic(X, scaled: Cameras, tracks, principal_point, shared_focal, solve):
    """From the scaled solution: one scale for all views, folded into the cloud."""
    s = scaled.scale()
    common = float(np.exp(np.mean(np.log(s))))
    R = scaled.current_rotations()
    start = affine_cameras("orthographic", R[:, :2], np.ones(len(s)), scaled.params[:, 3:5])
    return adjust(X * common, start, tracks, **solve)


def _perspective(X, scaled: Cameras, tracks, principal_point, shared_focal, solve):
    """From the scaled solution, at several focal lengths and in both depth
    orders (weak perspective cannot tell a cloud from its mirror image in depth;
    a pinhole can): a short solve from each, then the best one to the end."""
    z = tracks.z
    c = (z.min(axis=0) + z.max(axis=0)) / 2 if principal_point is None \
        else np.asarray(principal_point, dtype=float)
    size = _image_size(tracks)
    R, s, t = scaled.current_rotations(), scaled.scale(), scaled.params[:, 3:5]
    centre = X.mean(axis=0)  # the pinhole matches the weak perspective at the centroid
    X, t = X - centre, t + s[:, None] * (R[:, :2] @ centre)
    X = _bounded_depth(X)
    starts = []
    for mirror in (1.0, -1.0):  # -X seen through -R[:2] gives the same weak-perspective images
        for factor in _FOCAL_STARTS:
            cameras = affine_cameras("perspective", mirror * R[:, :2], s, t, focal=factor * size,
                                     principal_point=c, shared_focal=shared_focal)
            starts.append(((_in_front(mirror * X, cameras, tracks), cameras), None))
    return _best_of(starts, tracks, solve)[0]


def _in_front(X: np.ndarray, cameras: Cameras, tracks: Tracks, keep: float = 0.5) -> np.ndarray:
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
    return _sum_by(tracks.view, values, tracks.n_views) / counts[:, None]


# -- bundle adjustment -----------------------------------------------------------

def _robust_weights(squared: np.ndarray, loss: str, scale: float):
    """rho(s) summed and rho'(s) per observation, s = ||r||^2 / scale^2 (scipy's losses)."""
    s = squared / scale ** 2
    if loss == "l2":
        return float(squared.sum()), np.ones_like(s)
    if loss == "huber":
        root = np.sqrt(np.maximum(s, 1))
        rho, weight = np.where(s <= 1, s, 2 * root - 1), np.where(s <= 1, 1.0, 1 / root)
    elif loss == "soft_l1":
        rho, weight = 2 * (np.sqrt(1 + s) - 1), 1 / np.sqrt(1 + s)
    else:  # cauchy
        rho, weight = np.log1p(s), 1 / (1 + s)
    return float(scale ** 2 * rho.sum()), weight


class _Structure:
    """Index arrays of the bundle's normal equations, fixed for one set of tracks:
    each observation's camera columns, where its block of the camera system
    goes, and the sparsity of Y (rows: a point's 3 axes; columns: cameras)."""

    def __init__(self, tracks: Tracks, cameras: Cameras):
        K, pv, ns = tracks.n_views, cameras.per_view, cameras.shared.size
        self.size = K * pv + ns
        self.cols = np.concatenate([pv * tracks.view[:, None] + np.arange(pv),
                                    np.broadcast_to(K * pv + np.arange(ns), (len(tracks.view), ns))],
                                   axis=1)  # (T, pv + ns)
        # each (observation, axis) gives the c entries of row 3 * point + axis
        c = self.cols.shape[1]
        self.y_order = _row_order(tracks.point, tracks.n_points)
        counts = np.repeat(np.bincount(tracks.point, minlength=tracks.n_points), 3) * c
        self.y_indptr = np.concatenate([[0], np.cumsum(counts)])
        self.y_indices = self.cols[self.y_order // 3].ravel()
        # a view's observations share their camera columns: its block of the
        # camera system is one c x c product, placed at these columns
        self.view_rows = [np.flatnonzero(tracks.view == k) for k in range(K)]  # once, not per step
        self.view_cols = [np.concatenate([pv * k + np.arange(pv), K * pv + np.arange(ns)])
                          for k in range(K)]

    def camera_system(self, weight: np.ndarray, d_c: np.ndarray) -> np.ndarray:
        """V = sum_t d_c^T w d_c, accumulated view by view (no T x c x c array)."""
        V = np.zeros((self.size, self.size))
        c = d_c.shape[2]
        for rows, cols in zip(self.view_rows, self.view_cols):
            if len(rows):
                J = d_c[rows].reshape(-1, c)
                V[np.ix_(cols, cols)] += (np.repeat(weight[rows], 2)[:, None] * J).T @ J
        return V


def _row_order(point: np.ndarray, n_points: int) -> np.ndarray:
    """argsort(3 * point[:, None] + [0, 1, 2]) (stable), as a counting sort:
    row 3p + a lists (t, a) for the observations t of point p in order."""
    by_point = np.argsort(point, kind="stable")
    counts = np.bincount(point, minlength=n_points)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p = point[by_point]
    rank = np.arange(len(point)) - start[p]  # position within its point's observations
    order = np.empty(3 * len(point), dtype=np.int64)
    for a in range(3):
        order[3 * start[p] + a * counts[p] + rank] = 3 * by_point + a
    return order


def adjust(X: np.ndarray, cameras: Cameras, tracks: Tracks, loss: str = "l2",
           loss_scale: float = 1.0, max_iter: int = 100, tol: float = 1e-12,
           frozen: np.ndarray | None = None):
    """Levenberg-Marquardt on E(X, C) with the points eliminated (Schur complement).

    Each iteration solves the damped normal equations of the (robustly
    reweighted) Gauss-Newton step: the 3x3 block of every point is inverted
    and the reduced camera system, K * (5..7) unknowns, solved densely. That
    is bundle adjustment's standard solver and why its cost is linear in the
    observations.

    ``frozen`` (a mask over ``cameras.vector()``) holds camera parameters
    fixed: known rotations. Returns X, cameras, the RMS history and whether it
    converged.
    """
    structure = _Structure(tracks, cameras)
    free = np.ones(structure.size) if frozen is None else (~np.asarray(frozen)).astype(float)
    N, view, point = tracks.n_points, tracks.view, tracks.point
    unseen = np.bincount(point, minlength=N) == 0  # points without observations stay put
    cameras = cameras.reanchored()
    lam = 1e-4

    def evaluate(Xv, cam):
        r = cam.project(Xv, view, point) - tracks.z
        cost, weight = _robust_weights(np.sum(r ** 2, axis=1), loss, loss_scale)
        return r, (cost if np.isfinite(cost) else np.inf), weight

    r, cost, weight = evaluate(X, cameras)
    if not np.isfinite(cost) or not np.all(np.isfinite(X)):  # e.g. a point behind a camera
        return X, cameras, np.array([np.inf]), False
    history, converged, nu = [_rms(r)], False, 2.0
    if history[0] <= _EXACT * _image_size(tracks):  # exact already: nothing to descend
        return X, cameras, np.array(history), True
    for iteration in range(1, max_iter + 1):
        d_x, d_view, d_shared = cameras.jacobian_blocks(X, view, point)
        d_c = np.concatenate([d_view, d_shared], axis=2)  # (T, 2, c)
        d_c = d_c * free[structure.cols][:, None, :]
        wr = weight[:, None] * r
        wd_x = weight[:, None, None] * d_x  # batched matmuls: far faster than 3-operand einsum
        wd_xt = wd_x.transpose(0, 2, 1)
        U = _sum_by(point, wd_xt @ d_x, N)
        U[unseen] = np.eye(3)
        W = wd_xt @ d_c  # (T, 3, c)
        g_x = _sum_by(point, np.einsum("tai,ta->ti", d_x, wr), N)
        g_c = np.bincount(structure.cols.ravel(), minlength=structure.size,
                          weights=np.einsum("taj,ta->tj", d_c, wr).ravel())
        V = structure.camera_system(weight, d_c)
        while True:
            step = _damped_step(U, V, W, g_x, g_c, lam, structure, point)
            if step is not None:
                dx, dc, predicted = step
                trial_cam = cameras.with_vector(cameras.vector() + dc)
                trial_X = X + dx
                r_new, cost_new, weight_new = evaluate(trial_X, trial_cam)
                if np.isfinite(cost_new) and cost_new < cost:
                    break
            if lam > 1e16 or (step is not None and predicted <= 1e-15 * max(cost, 1e-300)):
                # no step lowers the cost any more: a minimum, to working precision
                return X, cameras, np.array(history), True
            lam, nu = lam * nu, nu * 2
        # Nielsen's update: shrink the damping as far as the model predicted well
        gain = (cost - cost_new) / max(predicted, 1e-300)
        lam, nu = lam * max(1 / 3, 1 - (2 * gain - 1) ** 3), 2.0
        decrease = cost - cost_new
        X, cameras, r, weight, cost = trial_X, trial_cam.reanchored(), r_new, weight_new, cost_new
        history.append(_rms(r))
        small_step = np.sqrt(np.sum(dx ** 2) + np.sum(dc ** 2)) <= tol * (1 + np.sqrt(np.sum(X ** 2)))
        if decrease <= tol * max(cost + decrease, 1e-300) or small_step or cost <= 1e-28:
            converged = True
            break
    return X, cameras, np.array(history), converged


def _schur_term(U_damped, W, structure, point):
    """sum_i W_i^T U_i^-1 W_i = Y^T Y, with Y the sparse stack of U_i^-1/2 W_i."""
    values, vectors = np.linalg.eigh(U_damped)
    root = np.einsum("nij,nj,nkj->nik", vectors, 1 / np.sqrt(values), vectors)  # U_i^-1/2
    data = np.matmul(root[point], W).reshape(-1, W.shape[2])[structure.y_order]
    Y = csr_matrix((data.ravel(), structure.y_indices, structure.y_indptr),
                   shape=(3 * len(U_damped), structure.size))
    Y.sum_duplicates()  # the shared columns (focal length) recur within a row
    if Y.shape[0] * Y.shape[1] <= _DENSE_Y:  # few points: BLAS on the dense Y is faster
        Y = Y.toarray()
        return Y.T @ Y
    return (Y.T @ Y).toarray()


def _damped_step(U, V, W, g_x, g_c, lam, structure, point):
    """The Levenberg-Marquardt step (dx, dc) by the Schur complement and the cost
    decrease the Gauss-Newton model predicts for it, or None if the damped
    reduced system is not positive definite."""
    D_x = np.einsum("nii->ni", U)
    D_x = D_x + 1e-12 * D_x.max(axis=1, keepdims=True)
    D_c = np.diag(V) + 1e-12 * max(np.diag(V).max(initial=0.0), 1e-300)
    U_damped = U.copy()
    U_damped[:, np.arange(3), np.arange(3)] += lam * D_x
    try:
        U_inv = np.linalg.inv(U_damped)
    except np.linalg.LinAlgError:
        return None
    S = V - _schur_term(U_damped, W, structure, point) if structure.size else V
    S[np.diag_indices_from(S)] += lam * D_c
    Ug = np.einsum("nij,nj->ni", U_inv, g_x)
    rhs = g_c - np.bincount(structure.cols.ravel(), minlength=structure.size,
                            weights=np.einsum("tic,ti->tc", W, Ug[point]).ravel())
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
        return None
    try:
        dc = -cho_solve(cho_factor(S), rhs) if len(rhs) else rhs  # known cameras: none
    except np.linalg.LinAlgError:
        return None
    coupling = _sum_by(point, np.einsum("tic,tc->ti", W, dc[structure.cols]), len(U))
    dx = -np.einsum("nij,nj->ni", U_inv, g_x + coupling)
    # cost = sum of rho: the model's decrease is -g.d + lam d.D.d (g = J^T W r)
    predicted = float(-np.sum(g_x * dx) - g_c @ dc + lam * (np.sum(D_x * dx ** 2) + D_c @ dc ** 2))
    return dx, dc, predicted


def _rms(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(residual.reshape(-1, 2) ** 2, axis=1))))
