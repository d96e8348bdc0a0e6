"""Points from cameras: linear triangulation, and its robust form for tracks
with wrong matches in them.

Every camera model gives a 3x4 matrix P (``Cameras.projection_matrices``),
and an observation z of x under P gives two linear equations (the DLT):
exact for the affine models, the algebraic error for a pinhole.
"""

from __future__ import annotations

import numpy as np

from mpe3d.solvers.linalg import pinv_psd, sum_by
from mpe3d.solvers.sfm.kernels import lowest_cosines

PAIRS = 30  # two-view hypotheses tried per point
_REFINEMENTS = 2  # least-squares refits on a hypothesis's inliers
POINT_ITERATIONS = 30  # Levenberg-Marquardt steps of adjusted_points, at most


def dlt_rows(P, view, z):
    """Two linear equations A x = b per observation of a 3x4 camera: (T, 2, 3), (T, 2)."""
    P = P[view]
    A = P[:, :2, :3] - z[:, :, None] * P[:, 2:3, :3]
    b = z * P[:, 2:3, 3] - P[:, :2, 3]
    return A, b


def least_squares_points(A, b, point, n_points):
    """x_i minimising sum_t ||A_t x_i - b_t||^2 over each point's observations."""
    lhs = sum_by(point, np.einsum("tai,taj->tij", A, A), n_points)
    rhs = sum_by(point, np.einsum("tai,ta->ti", A, b), n_points)
    return np.einsum("nij,nj->ni", pinv_psd(lhs), rhs)


def adjusted_points(X, cameras, tracks, points, max_iter: int = POINT_ITERATIONS,
                    tol: float = 1e-10) -> np.ndarray:
    """X with the ``points`` ((N,) bool) moved to their least-squares positions
    under fixed ``cameras``, from where they stand: Levenberg-Marquardt on the
    reprojection error, a 3x3 system and a damping per point, so that a point
    whose depth the rays barely fix converges at its own pace instead of
    holding back a bundle's shared damping. A step is kept only where it
    lowers its point's error."""
    rows = points[tracks.point]
    if not rows.any():
        return X
    ids = np.flatnonzero(points)  # the work is theirs alone, however many points there are
    view, point, z, n = tracks.view[rows], np.searchsorted(ids, tracks.point[rows]), tracks.z[rows], len(ids)

    def errors(x):
        r = cameras.project(x, view, point) - z  # nan behind a camera: never lower
        return r, np.bincount(point, weights=np.sum(r ** 2, axis=1), minlength=n)

    x, lam = X[ids], np.full(n, 1e-3)
    r, cost = errors(x)
    for _ in range(max_iter):
        d_x = cameras.jacobian_blocks(x, view, point)[0]
        U = sum_by(point, np.einsum("tai,taj->tij", d_x, d_x), n)
        g = sum_by(point, np.einsum("tai,ta->ti", d_x, r), n)
        diagonal = np.einsum("nii->ni", U)
        damping = lam[:, None] * diagonal + 1e-12 * diagonal.max(axis=1, keepdims=True)
        step = -np.linalg.solve(U + damping[:, :, None] * np.eye(3), g[:, :, None])[:, :, 0]
        r_new, cost_new = errors(x + step)
        better = cost_new < cost
        x[better] += step[better]
        r = np.where(better[point][:, None], r_new, r)
        decrease = float(np.sum(cost[better] - cost_new[better]))
        cost = np.where(better, cost_new, cost)
        lam = np.where(better, lam / 3, lam * 10)
        if decrease <= tol * float(cost.sum()):
            break
    X = X.copy()
    X[ids] = x
    return X


def robust_points(X, cameras, tracks, points, tau, seed: int = 0):
    """The points ``points`` triangulated again under fixed ``cameras``, each from
    the observations that agree: (X, outlying (T,) bool for their observations).

    For each point, RANSAC over pairs of its observations (``PAIRS`` of them)
    and its current position, scored by the truncated cost sum min(r, tau)^2
    over all its observations (MSAC); the best is refitted on its inliers. A
    point moves only where this lowers its cost, so a point that followed a
    wrong match (its right observations dropped) goes back to the right ones,
    and observations dropped while their point was dragged are taken back.
    Observations of other points come back False.
    """
    points = points[np.bincount(tracks.point, minlength=tracks.n_points)[points] >= 2]
    outlying = np.zeros(len(tracks.view), dtype=bool)
    if not len(points):
        return X, outlying
    rows = np.flatnonzero(np.isin(tracks.point, points))
    rows = rows[np.argsort(tracks.point[rows], kind="stable")]
    points, start, count = np.unique(tracks.point[rows], return_index=True, return_counts=True)
    owner = np.repeat(np.arange(len(points)), count)  # rows' index into points
    P = cameras.projection_matrices()
    hypotheses = np.concatenate([X[points][:, None], _pair_hypotheses(
        P, tracks, rows, start, count, np.random.default_rng(seed))], axis=1)  # current first
    cost = _costs(cameras, tracks, rows, start, count, hypotheses, tau)
    best = hypotheses[np.arange(len(points)), np.argmin(cost, axis=1)]
    best_cost = _cost(cameras, tracks, rows, owner, best, tau)
    for _ in range(_REFINEMENTS):
        inlier = _lengths(cameras, tracks, rows, owner, best) <= tau
        if not inlier.any():  # no observation agrees with any other: nothing to refit
            break
        A, b = dlt_rows(P, tracks.view[rows[inlier]], tracks.z[rows[inlier]])
        refit = least_squares_points(A, b, owner[inlier], len(points))
        refit_cost = _cost(cameras, tracks, rows, owner, refit, tau)
        better = (np.bincount(owner[inlier], minlength=len(points)) >= 2) & (refit_cost <= best_cost)
        best[better], best_cost[better] = refit[better], refit_cost[better]
    moved = best_cost < cost[:, 0]
    X = X.copy()
    X[points[moved]] = best[moved]
    outlying[rows] = _lengths(cameras, tracks, rows, owner, X[points]) > tau
    return X, outlying


def _pair_hypotheses(P, tracks, rows, start, count, rng):
    """(n, PAIRS, 3): each point from two of its observations (random pairs)."""
    first = rng.integers(0, count[:, None], (len(count), PAIRS))
    second = (first + rng.integers(1, count[:, None], (len(count), PAIRS))) % count[:, None]
    pairs = [rows[start[:, None] + k].ravel() for k in (first, second)]
    A, b = zip(*(dlt_rows(P, tracks.view[r], tracks.z[r]) for r in pairs))
    x = np.einsum("hij,hj->hi", np.linalg.pinv(np.concatenate(A, axis=1)), np.concatenate(b, axis=1))
    return x.reshape(len(count), PAIRS, 3)


def _costs(cameras, tracks, rows, start, count, hypotheses, tau):
    """(n, H): the truncated cost of every hypothesis over its point's observations."""
    n, H = hypotheses.shape[:2]
    block = np.repeat(count, H)  # one block of the point's observations per hypothesis
    which = np.repeat(np.arange(n * H), block)
    within = np.arange(len(which)) - np.repeat(np.cumsum(block) - block, block)
    obs = rows[np.repeat(start, H * count) + within]
    u = cameras.project(hypotheses.reshape(-1, 3), tracks.view[obs], which) - tracks.z[obs]
    truncated = np.minimum(np.nan_to_num(np.linalg.norm(u, axis=1), nan=np.inf), tau) ** 2
    return np.bincount(which, weights=truncated, minlength=n * H).reshape(n, H)


def _lengths(cameras, tracks, rows, owner, x):
    u = cameras.project(x, tracks.view[rows], owner) - tracks.z[rows]
    return np.nan_to_num(np.linalg.norm(u, axis=1), nan=np.inf)  # behind a camera: no image


def _cost(cameras, tracks, rows, owner, x, tau):
    truncated = np.minimum(_lengths(cameras, tracks, rows, owner, x), tau) ** 2
    return np.bincount(owner, weights=truncated, minlength=len(x))


def ray_directions(P: np.ndarray, X: np.ndarray, view: np.ndarray, point: np.ndarray):
    """Unit directions of the rays from each observation's camera to its point,
    and whether they are lines only (affine cameras, whose centre is at infinity:
    a view and its opposite see the same line).

    The camera centre is P's null vector C: for a pinhole the ray runs from
    C[:3] / C[3] to x; for an affine camera (C[3] = 0) along C[:3] itself.
    """
    centre = np.linalg.svd(P)[2][:, -1, :]  # (K, 4), P C = 0
    affine = np.abs(centre[:, 3]) <= 1e-9 * np.linalg.norm(centre[:, :3], axis=1)
    if affine.all():
        rays = centre[view, :3]
    else:
        rays = X[point] - centre[view, :3] / centre[view, 3:4]
    norm = np.linalg.norm(rays, axis=1, keepdims=True)
    return rays / np.where(norm > 0, norm, 1.0), bool(affine.all())


def widest_angles(rays: np.ndarray, point: np.ndarray, n_points: int, lines: bool = False):
    """(n_points,) the widest angle, in degrees, between any two rays of each
    point (0 for a point with fewer than two): COLMAP's triangulation angle."""
    order = np.argsort(point, kind="stable")
    lowest = lowest_cosines(np.ascontiguousarray(rays[order], dtype=float), point[order].astype(np.int64),
                            n_points, bool(lines))
    return np.degrees(np.arccos(np.clip(lowest, -1.0, 1.0)))
