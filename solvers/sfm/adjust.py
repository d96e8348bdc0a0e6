"""Bundle adjustment's solver: Levenberg-Marquardt with the points eliminated.

Minimises the (robust) reprojection error E(X, C) = sum_t rho(||u_k(x_i; C_k)
- z_t||^2) over the points and the cameras of :mod:`.cameras`, with the
Schur complement: a 3x3 block per point, a dense K * (5..7) camera system.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import threadpool_limits

from mpe3d.solvers import threads
from mpe3d.solvers.linalg import sum_by
from mpe3d.solvers.sfm.cameras import Cameras
from mpe3d.solvers.sfm.kernels import inverse_roots, reduced_system, transposed_products, whitened_blocks
from mpe3d.solvers.sfm.tracks import EXACT_RMS, Tracks, image_size, rms

ROUND_TOL = 1e-6  # a solve between two rounds (of dropping wrong matches, of a start) stops here
# ... or after this many iterations: a round only tells the next one which
# residuals are long (11 photos, 78,000 observations: rounds of 34-38
# iterations, 4 s each, before the solve to the end that finishes them anyway)
ROUND_ITERATIONS = 10


@dataclasses.dataclass(frozen=True, eq=False)
class LMOptions:
    """The Levenberg-Marquardt options every :func:`adjust` of one problem shares.

    ``loss`` is rho of the squared residual length (scipy's names), with
    ``loss_scale`` in pixels; a solve stops after ``max_iter`` iterations or
    when one lowers the cost by less than ``tol`` of it. ``frozen`` (a mask
    over ``Cameras.vector()``) holds camera parameters fixed: known rotations.
    """

    loss: str = "l2"
    loss_scale: float = 1.0
    max_iter: int = 100
    tol: float = 1e-10
    frozen: np.ndarray | None = None

    def loose(self) -> "LMOptions":
        """Solved to ROUND_TOL at most: a round whose result the next round moves anyway."""
        return dataclasses.replace(self, tol=max(self.tol, ROUND_TOL))

    def round(self) -> "LMOptions":
        """A round's solve: loose, and ROUND_ITERATIONS at most."""
        return self.loose().short(ROUND_ITERATIONS)

    def short(self, iterations: int) -> "LMOptions":
        """At most ``iterations``: a start that is only judged, or raced."""
        return dataclasses.replace(self, max_iter=min(self.max_iter, iterations))

    def thawed(self) -> "LMOptions":
        """Every camera parameter free (the frozen mask fits one camera array only)."""
        return dataclasses.replace(self, frozen=None)


class Fit(NamedTuple):
    """One solve: the points, the cameras, the RMS residual (pixels) after each
    iteration, and whether it converged."""

    X: np.ndarray
    cameras: Cameras
    history: np.ndarray
    converged: bool


def one_blas_thread(func):
    """Run ``func`` on one BLAS thread: its matrices are small (3x3 blocks, a
    K*6 camera system), where threads cost more than they give (backyard, 100
    views: 2.8 s on one thread, 5.4 s on two)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with threadpool_limits(1):
            return func(*args, **kwargs)
    return wrapper


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


def robust_cost(squared: np.ndarray, lm: LMOptions) -> float:
    """sum_t rho(||r_t||^2): the cost :func:`adjust` minimises, of squared residual lengths."""
    return _robust_weights(squared, lm.loss, lm.loss_scale)[0]


class _Structure:
    """Index arrays of the bundle's normal equations, fixed for one set of tracks:
    each observation's camera columns, where its block of the camera system
    goes, and each point's observations (the rows of its block of Y)."""

    def __init__(self, tracks: Tracks, cameras: Cameras):
        K, pv, ns = tracks.n_views, cameras.per_view, cameras.shared.size
        self.size = K * pv + ns
        self.cols = np.concatenate([pv * tracks.view[:, None] + np.arange(pv),
                                    np.broadcast_to(K * pv + np.arange(ns), (len(tracks.view), ns))],
                                   axis=1)  # (T, pv + ns)
        # the observations grouped by point, each point's by view (so the Schur
        # kernel fills the upper blocks), their points and views in that order,
        # fixed for every step, and where each point's begin
        self.by_point = np.lexsort((tracks.view, tracks.point))
        self.point_by_point = tracks.point[self.by_point]
        self.view_by_point = tracks.view[self.by_point]
        self.blocks = np.empty((K, K, pv, pv))  # the Schur kernel's workspace, every step
        self.point_starts = np.concatenate(
            [[0], np.cumsum(np.bincount(tracks.point, minlength=tracks.n_points))])
        # a view's observations share their camera columns: its block of the
        # camera system is one c x c product; its rows by one stable sort, not
        # K scans of every observation (250 views: 10 ms of each solve's
        # set-up), the same index arrays
        self.view_rows = np.split(np.argsort(tracks.view, kind="stable"),
                                  np.cumsum(np.bincount(tracks.view, minlength=K))[:-1])
        self.per_view = pv

    def camera_system(self, weight: np.ndarray, d_c: np.ndarray) -> np.ndarray:
        """V = sum_t d_c^T w d_c, accumulated view by view (no T x c x c array).
        A view's block is added by slices (its own columns are one range, the
        shared ones the last): the same additions, in the same order, as by
        np.ix_, whose index arrays cost more than the product at 250 views."""
        V = np.zeros((self.size, self.size))
        c = d_c.shape[2]
        pv = self.per_view
        base = self.size - (c - pv)  # the shared columns'
        for k, rows in enumerate(self.view_rows):
            if len(rows):
                J = d_c[rows].reshape(-1, c)
                block = (np.repeat(weight[rows], 2)[:, None] * J).T @ J
                own = slice(k * pv, (k + 1) * pv)
                V[own, own] += block[:pv, :pv]
                if c > pv:
                    V[own, base:] += block[:pv, pv:]
                    V[base:, own] += block[pv:, :pv]
                    V[base:, base:] += block[pv:, pv:]
        return V


def adjust(X: np.ndarray, cameras: Cameras, tracks: Tracks, options: LMOptions = LMOptions()) -> Fit:
    """Levenberg-Marquardt on E(X, C) with the points eliminated (Schur complement).

    Each iteration solves the damped normal equations of the (robustly
    reweighted) Gauss-Newton step: the 3x3 block of every point is inverted
    and the reduced camera system, K * (5..7) unknowns, solved densely. That
    is bundle adjustment's standard solver and why its cost is linear in the
    observations.

    ``options`` (:class:`LMOptions`): the loss, the iterations and the
    parameters held fixed.
    """
    loss, loss_scale, tol, frozen = options.loss, options.loss_scale, options.tol, options.frozen
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
        return Fit(X, cameras, np.array([np.inf]), False)
    history, converged, nu = [rms(r)], False, 2.0
    if history[0] <= EXACT_RMS * image_size(tracks):  # exact already: nothing to descend
        return Fit(X, cameras, np.array(history), True)
    for _ in range(options.max_iter):
        d_x, d_view, d_shared = cameras.jacobian_blocks(X, view, point)
        d_c = np.concatenate([d_view, d_shared], axis=2) if d_shared.shape[2] else d_view  # (T, 2, c)
        if frozen is not None:
            d_c = d_c * free[structure.cols][:, None, :]
        wr = weight[:, None] * r
        wd_x = weight[:, None, None] * d_x
        d_x, d_c = np.ascontiguousarray(d_x), np.ascontiguousarray(d_c)  # (the kernel's layout)
        U = sum_by(point, transposed_products(wd_x, d_x), N)
        U[unseen] = np.eye(3)
        W = transposed_products(wd_x, d_c)  # (T, 3, c)
        g_x = sum_by(point, np.einsum("tai,ta->ti", d_x, wr), N)
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
                return Fit(X, cameras, np.array(history), True)
            lam, nu = lam * nu, nu * 2
        # Nielsen's update: shrink the damping as far as the model predicted well
        gain = (cost - cost_new) / max(predicted, 1e-300)
        lam, nu = lam * max(1 / 3, 1 - (2 * gain - 1) ** 3), 2.0
        decrease = cost - cost_new
        X, cameras, r, weight, cost = trial_X, trial_cam.reanchored(), r_new, weight_new, cost_new
        history.append(rms(r))
        small_step = np.sqrt(np.sum(dx ** 2) + np.sum(dc ** 2)) <= tol * (1 + np.sqrt(np.sum(X ** 2)))
        if decrease <= tol * max(cost + decrease, 1e-300) or small_step or cost <= 1e-28:
            converged = True
            break
    return Fit(X, cameras, np.array(history), converged)


def _reduced_system(V, root, W, structure):
    """The upper triangle of S = V - sum_i W_i^T U_i^-1 W_i = V - Y^T Y, with Y
    the stack of M_i W_i (``root``: M_i^T M_i = U_i^-1), by the compiled pass
    over each point's pairs of observations
    (:func:`mpe3d.solvers.sfm.kernels.reduced_system`)."""
    Y = whitened_blocks(root, W, structure.point_by_point, structure.by_point)  # (T, 3, c), by point
    return reduced_system(V, Y, structure.view_by_point, structure.point_starts, structure.blocks,
                          threads.count())


def _damped_step(U, V, W, g_x, g_c, lam, structure, point):
    """The Levenberg-Marquardt step (dx, dc) by the Schur complement and the cost
    decrease the Gauss-Newton model predicts for it, or None if the damped
    reduced system is not positive definite."""
    D_x = np.einsum("nii->ni", U)
    D_x = D_x + 1e-12 * D_x.max(axis=1, keepdims=True)
    D_c = np.diag(V) + 1e-12 * max(np.diag(V).max(initial=0.0), 1e-300)
    U_damped = U.copy()
    U_damped[:, np.arange(3), np.arange(3)] += lam * D_x
    root, U_inv, definite = inverse_roots(U_damped)
    if not definite:
        return None
    S = _reduced_system(V, root, W, structure) if structure.size else V.copy()
    S[np.diag_indices_from(S)] += lam * D_c
    Ug = np.einsum("nij,nj->ni", U_inv, g_x)
    rhs = g_c - np.bincount(structure.cols.ravel(), minlength=structure.size,
                            weights=np.einsum("tic,ti->tc", W, Ug[point]).ravel())
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
        return None
    try:
        # S is checked finite above and not used again: factorised in place
        dc = -cho_solve(cho_factor(S, overwrite_a=True, check_finite=False), rhs, check_finite=False) \
            if len(rhs) else rhs  # known cameras: none
    except np.linalg.LinAlgError:
        return None
    coupling = sum_by(point, np.einsum("tic,tc->ti", W, dc[structure.cols]), len(U))
    dx = -np.einsum("nij,nj->ni", U_inv, g_x + coupling)
    # cost = sum of rho: the model's decrease is -g.d + lam d.D.d (g = J^T W r)
    predicted = float(-np.sum(g_x * dx) - g_c @ dc + lam * (np.sum(D_x * dx ** 2) + D_c @ dc ** 2))
    return dx, dc, predicted
