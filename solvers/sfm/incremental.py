"""An incremental weak-perspective start that wrong matches cannot bend.

A global start (the affine factorisation of every view at once) is a
least-squares fit of all observations: the wrong matches that the two-view
test misses still drag it, and on long sequences with missing data its
alternating sweeps stall in a folded shape (dino with 80 observations removed:
median residual 1.8 px against 0.53). Structure from motion's answer is to grow
the reconstruction: a seed of three views, then, round by round, the views that
see the most placed points are resected, the points seen by two registered
views triangulated, and what is there bundle-adjusted. Each step is robust:

- the seed's shared points and each resection are fitted by RANSAC (their
  rows lie on a 3D affine subspace, :func:`.epipolar.off_affine_subspace`);
- the bundle adjustment of each round uses a Cauchy loss at 3 robust sigmas,
  so a wrong match left in does not pull, and the observations beyond
  ``threshold`` sigmas (and beyond ``FLOOR`` of the image, so that a pinhole
  scene's weak-perspective misfit is no wrong match) are left out of the
  next round;
- a point with left-out observations is triangulated again by RANSAC over
  pairs of them (:func:`.triangulation.robust_points`): one placed from two
  views, one of them a wrong match, follows it, and its right observations
  in the views added later would be the ones left out.

It returns the start and the observations it left out; those are suspects, as
the two-view test's are (:func:`.bundle.bundle_adjust` takes back the ones its
final fit explains).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mpe3d.options import OUTLIER_THRESHOLD
from mpe3d.solvers.factorize import metric_upgrade_pd
from mpe3d.solvers.linalg import fit_views, rows_of
from mpe3d.solvers.sfm.adjust import LMOptions, adjust
from mpe3d.solvers.sfm.cameras import Cameras, affine_cameras
from mpe3d.solvers.sfm.epipolar import off_affine_subspace, off_affine_subspace_each
from mpe3d.solvers.sfm.tracks import Tracks, image_size, residual_lengths, robust_sigma
from mpe3d.solvers.sfm.triangulation import least_squares_points, robust_points
from mpe3d.solvers.stress import project_rows

MIN_RESECTION = 6  # placed points a view must see to be resected
# Views resected together: all those seeing at least this share of the most
# placed points any unregistered view sees (fewer rounds than one at a time).
BATCH = 0.75
# Levenberg-Marquardt iterations per round: a round starts from the last one's
# solution plus a few views, and the start is solved to the end afterwards, so
# a round only needs the residuals to tell wrong matches. 3, 5 and 15 give the
# same fits of house, dino and backyard, with and without 3% wrong matches;
# on COLMAP's 250-photo spiral (31 rounds) 5 took 4 s more than 3 for a final
# RMS 0.3% higher, and 15 three times as long.
ROUND_ITERATIONS = 3
CAUCHY_SIGMAS = 3.0  # the Cauchy loss's scale, in robust sigmas
# A weak-perspective view of a pinhole scene misses by up to this share of the
# image (VGG's house: 4.8% at the tenth largest residual); a start only needs
# the gross errors left out.
FLOOR = 0.05


class Grown(NamedTuple):
    """The incremental start: points, scaled cameras, and the observations left out."""

    X: np.ndarray
    cameras: Cameras
    left_out: np.ndarray  # (T,) bool


def incremental_start(tracks, threshold: float = OUTLIER_THRESHOLD, tol: float = 1e-6,
                      random_state: int = 0) -> Grown | None:
    """(X, scaled cameras, left_out) grown from a seed of three views, or None
    when there are fewer, no three share 4 points or some view is never reached.

    ``left_out`` (T,) marks the observations beyond ``threshold`` robust sigmas
    of the last round (and beyond ``FLOOR`` of the image). ``random_state``
    seeds the robust fits' samples."""
    K, N = tracks.n_views, tracks.n_points
    if K < 3:  # two views are their own seed: the factorisation's start is all there is
        return None
    floor = FLOOR * image_size(tracks)
    seen = np.zeros((K, N), dtype=bool)
    seen[tracks.view, tracks.point] = True
    seed = _seed_views(seen)
    X, P, s, t = np.zeros((N, 3)), np.zeros((K, 2, 3)), np.ones(K), np.zeros((K, 2))
    common = _seed(tracks, seen, seed, floor, X, P, s, t, random_state)
    if common is None:
        return None
    registered = np.zeros(K, dtype=bool)
    registered[seed] = True
    placed = np.zeros(N, dtype=bool)
    placed[common] = True
    left_out = np.zeros(len(tracks.view), dtype=bool)
    sigma = None
    while True:
        _triangulate(tracks, registered, placed, X, P, s, t)
        rows = registered[tracks.view] & placed[tracks.point]
        cameras = affine_cameras("scaled", P, s, t)
        sigma = sigma or robust_sigma(X, cameras, tracks, rows)
        _adjust_round(tracks, rows & ~left_out, X, P, s, t, CAUCHY_SIGMAS * sigma, tol)
        cameras = affine_cameras("scaled", P, s, t)
        sigma = robust_sigma(X, cameras, tracks, rows)
        left_out = _left_out(tracks, rows, X, cameras, max(threshold * sigma, floor), random_state)
        reach = np.bincount(tracks.view[placed[tracks.point]], minlength=K)
        reach[registered] = -1
        if reach.max() < MIN_RESECTION:
            break
        added = np.flatnonzero(reach >= max(MIN_RESECTION, BATCH * reach.max()))
        _resect(tracks, added, placed, floor, X, P, s, t, random_state)
        registered[added] = True
    if not registered.all():
        return None
    X[~placed] = X[placed].mean(axis=0)
    # the cloud in pixels at the views' mean scale, as the factorisation's start
    # gives it: weak perspective leaves its size free, an orthographic camera not
    norm = float(np.exp(np.mean(np.log(s))))
    return Grown(X * norm, affine_cameras("scaled", P, s / norm, t), left_out)


def _left_out(tracks, rows, X, cameras, tau, random_state):
    """(T,) bool: the observations ``rows`` beyond ``tau``, after the points with
    any are triangulated again robustly (X in place)."""
    length = np.where(rows, np.nan_to_num(residual_lengths(X, cameras, tracks), nan=np.inf), 0)
    suspects = np.unique(tracks.point[length > tau])
    if not len(suspects):
        return length > tau
    sub = tracks.subset(rows)
    X[:] = robust_points(X, cameras, sub, suspects, tau, random_state)[0]
    length[rows] = np.nan_to_num(residual_lengths(X, cameras, sub), nan=np.inf)
    return length > tau


def _seed_views(seen):
    """The two views sharing the most points and the third sharing most of those."""
    shared = seen.astype(np.int32) @ seen.T.astype(np.int32)
    np.fill_diagonal(shared, -1)
    a, b = np.unravel_index(np.argmax(shared), shared.shape)
    third = seen[:, seen[a] & seen[b]].sum(axis=1)
    third[[a, b]] = -1
    return [int(a), int(b), int(np.argmax(third))]


def _seed(tracks, seen, seed, floor, X, P, s, t, random_state):
    """The seed views' metric structure, into X, P, s, t: the robust rank-3
    factorisation of their shared points, upgraded; returns the points placed."""
    common = np.flatnonzero(seen[seed].all(axis=0))
    if len(common) < 4:
        return None
    W = np.hstack([rows_of(tracks.point[tracks.view == k], tracks.z[tracks.view == k], common)
                   for k in seed])
    inliers = ~off_affine_subspace(W, floor=floor, rng=np.random.default_rng(random_state))
    common, W = common[inliers], W[inliers]
    if len(common) < 4:
        return None
    mean = W.mean(axis=0)
    U, S, Vt = np.linalg.svd(W - mean, full_matrices=False)
    L = Vt[:3].T.reshape(3, 2, 3).transpose(0, 2, 1)  # (3, 3, 2): z = L_k^T x + t_k
    A = metric_upgrade_pd(L)
    X[common] = (U[:, :3] * S[:3]) @ np.linalg.inv(A).T
    P[seed], s[seed] = _scaled_rows(np.einsum("ia,kib->kba", A, L))
    t[seed] = mean.reshape(3, 2)
    return common


def _scaled_rows(A):
    """The nearest orthonormal rows and the mean singular value of each (2, 3) A."""
    return project_rows(A), np.linalg.svd(A, compute_uv=False).mean(axis=1)


def _triangulate(tracks, registered, placed, X, P, s, t):
    """Place every point that two registered views see (linear least squares)."""
    in_registered = registered[tracks.view]
    new = ~placed & (np.bincount(tracks.point[in_registered], minlength=tracks.n_points) >= 2)
    if new.any():
        # the new points' observations alone: the others' systems, singular for
        # points seen once, went to the pseudo-inverse's SVD (200,000 points: 0.8 s)
        sub = tracks.subset(in_registered & new[tracks.point])
        ids = np.flatnonzero(new)
        rows = s[sub.view, None, None] * P[sub.view]
        X[ids] = least_squares_points(rows, sub.z - t[sub.view], np.searchsorted(ids, sub.point), len(ids))
        placed |= new


def _adjust_round(tracks, rows, X, P, s, t, scale, tol):
    """Bundle-adjust the registered views and placed points (Cauchy loss), in place."""
    views, view = np.unique(tracks.view[rows], return_inverse=True)
    points, point = np.unique(tracks.point[rows], return_inverse=True)
    sub = Tracks(view, point, tracks.z[rows], len(points), len(views))
    cameras = affine_cameras("scaled", P[views], s[views], t[views])
    X[points], cameras, _, _ = adjust(X[points], cameras, sub, LMOptions(
        loss="cauchy", loss_scale=scale, max_iter=ROUND_ITERATIONS, tol=tol))
    P[views], s[views] = cameras.current_rotations()[:, :2], cameras.scale()
    t[views] = cameras.params[:, 3:5]


def _resect(tracks, added, placed, floor, X, P, s, t, random_state):
    """Each added view's scaled camera from its placed points: a robust affine
    fit (the rows (x_i, z_i) lie on a 3D subspace of R^5), made orthonormal."""
    rows = np.isin(tracks.view, added) & placed[tracks.point]
    mine = [np.flatnonzero(rows & (tracks.view == k)) for k in added]
    far = off_affine_subspace_each([np.hstack([X[tracks.point[m]], tracks.z[m]]) for m in mine],
                                   floor=floor, seed=random_state)
    for m, f in zip(mine, far):
        rows[m[f]] = False
    L, origin = fit_views(X, tracks.view, tracks.point, tracks.z, tracks.n_views, rows)
    P[added], s[added] = _scaled_rows(L[added].transpose(0, 2, 1))
    t[added] = origin[added]
