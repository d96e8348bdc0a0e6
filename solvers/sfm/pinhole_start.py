"""A pinhole start grown view by view, as COLMAP grows its models.

The affine start (:mod:`.incremental`, :mod:`.factorize`) folds when photos
are taken close to the object from far apart (a chair from 1.5 diagonals,
30 degrees between photos): the weak perspective that it fits is too far from
the pinhole for bundle adjustment to find its way back. This start is
perspective from the first pair on:

1. the initial pair: among the pairs of views sharing the most tracks, the
   one with the most inliers of an essential matrix (LO-RANSAC, 4 px, by
   pycolmap at the start focal length) whose inliers meet at a median
   triangulation angle of at least :data:`INIT_ANGLE` degrees;
2. registration: the view seeing the most placed points is resected by
   P3P in LO-RANSAC and refined (pycolmap's absolute pose), then the tracks
   it completes are triangulated (DLT, kept when their rays meet at
   :data:`~.support.MIN_RAY_ANGLE` degrees or more and they reproject
   within :data:`MAX_ERROR` px);
3. bundle adjustment (ours, :func:`.adjust.adjust`, one focal length for
   all views) each time the model has grown by :data:`GROWTH`, observations
   beyond :data:`MAX_ERROR` px left out after it: COLMAP's filter.

Views it cannot register stay out (``registered`` False), as COLMAP's
mapper leaves them out. The start focal length is a trusted prior's, or
1.2 times the larger image side (COLMAP's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpe3d.solvers.degenerate import shared_points
from mpe3d.solvers.sfm import colmap
from mpe3d.solvers.sfm.adjust import LMOptions, adjust
from mpe3d.solvers.sfm.cameras import Cameras
from mpe3d.solvers.sfm.support import MIN_RAY_ANGLE
from mpe3d.solvers.sfm.tracks import Tracks
from mpe3d.solvers.sfm.triangulation import dlt_rows, least_squares_points, ray_directions, widest_angles

INIT_CANDIDATES = 8  # pairs sharing the most tracks, tried as the initial pair
RANSAC_TRIALS = 2000  # at most, per essential matrix or pose (COLMAP's 10,000 chase a raw pair's outliers)
INIT_ANGLE = 4.0  # degrees: the initial pair's median triangulation angle, at least
MIN_INLIERS = 30  # the initial pair's essential-matrix inliers, at least
E_MATCHES = 1000  # matches an initial pair's essential matrix is estimated from, at most
MIN_RESECTION = 12  # placed points a view must see, and P3P inliers it must have
MAX_ERROR = 4.0  # pixels: RANSAC's threshold and the filter's (COLMAP's)
GROWTH = 1.25  # bundle adjustment when the registered views grew by this factor
ROUND_OPTIONS = LMOptions(max_iter=20, tol=1e-6)  # the start's adjustments are not the last word


@dataclass
class PinholeStart:
    """Points and perspective cameras of the views registered, and what is in the model."""

    X: np.ndarray  # (N, 3)
    cameras: Cameras  # perspective, one focal length; unregistered views: identity
    placed: np.ndarray  # (N,) bool
    registered: np.ndarray  # (K,) bool
    kept: np.ndarray  # (T,) bool: observations within MAX_ERROR px of their placed point
    narrow: np.ndarray  # (N,) bool: unplaced only because their rays meet too narrowly


def _colmap_camera(focal, c, box) -> colmap.Camera:
    """COLMAP's camera of ours, ``box`` (width, height) pixels: :func:`.colmap.keypoint_box`."""
    return colmap.simple_camera("SIMPLE_PINHOLE", box[0], box[1], focal, c)


def _cameras(R, t, focal, c) -> Cameras:
    params = np.concatenate([np.zeros((len(R), 3)), t], axis=1)
    return Cameras("perspective", R.copy(), params, np.array([np.log(focal)]), np.asarray(c, dtype=float))


def pinhole_start(tracks: Tracks, principal_point, focal: float | None = None,
                  seed: int = 0) -> PinholeStart | None:
    """The start of the module doc, or None when no pair of views makes one."""
    c = np.asarray(principal_point, dtype=float)
    f = float(focal) if focal is not None else 1.2 * float(np.max(2 * np.abs(tracks.z - c)))
    box = colmap.keypoint_box(tracks.z, c)
    state = _initial(tracks, f, c, box, seed)
    if state is None:
        return None
    failed: set[int] = set()
    adjusted_at = 2
    while True:
        k = _next_view(tracks, state, failed)
        if k is None:
            break
        if not _resect(tracks, state, k, box, seed):
            failed.add(k)
            continue
        _triangulate(tracks, state)
        if state.registered.sum() >= GROWTH * adjusted_at:
            _adjust(tracks, state)
            adjusted_at = int(state.registered.sum())
            failed.clear()  # better cameras: try them again
    _adjust(tracks, state)
    return state


def _initial(tracks, f, c, box, seed) -> PinholeStart | None:
    K, N = tracks.n_views, tracks.n_points
    shared = shared_points(tracks.view, tracks.point, K, N)
    np.fill_diagonal(shared, 0)
    a_idx, b_idx = np.triu_indices(K, 1)
    order = np.argsort(-shared[a_idx, b_idx], kind="stable")[:INIT_CANDIDATES]
    camera = _colmap_camera(f, c, box)
    best, best_score = None, 0.0
    for a, b in zip(a_idx[order], b_idx[order]):
        # a pair's score is at most the points it shares: none after this can win
        if shared[a, b] < MIN_INLIERS or shared[a, b] <= best_score:
            break
        common = np.intersect1d(tracks.point[tracks.view == a], tracks.point[tracks.view == b])
        za, zb = _rows_of(tracks, a, common), _rows_of(tracks, b, common)
        # the essential matrix from E_MATCHES evenly spread matches at most, its
        # inliers among all (11 photos of 3,000 px: 8 pairs of ~4,000, 6.8 s)
        some = np.linspace(0, len(common) - 1, min(len(common), E_MATCHES)).round().astype(int)
        found = colmap.essential_matrix(tracks.z[za[some]], tracks.z[zb[some]], camera, max_error=MAX_ERROR,
                                        seed=seed, trials=RANSAC_TRIALS)
        if found is None or found[3] < MIN_INLIERS * len(some) / len(common):
            continue
        E, R_b, t_b, _ = found
        inliers = common[_on_epipolar_lines(E, tracks.z[za], tracks.z[zb], f, c)]
        if len(inliers) < MIN_INLIERS:
            continue
        state = _pair_state(tracks, a, b, (R_b, t_b), inliers, f, c)
        if state.placed.sum() < MIN_INLIERS:
            continue
        rays, point, lines = _rays(tracks, state, np.flatnonzero(state.placed))
        angles = widest_angles(rays, point, N, lines)[state.placed]
        score = state.placed.sum() * min(1.0, float(np.median(angles)) / INIT_ANGLE)
        if score > best_score:
            best, best_score = state, score
    if best is None:
        return None
    _triangulate(tracks, best)
    _adjust(tracks, best)
    return best


def _on_epipolar_lines(E, za, zb, f, c) -> np.ndarray:
    """(n,) bool: the matches (za, zb) whose Sampson distance to the essential
    matrix E is within MAX_ERROR px (COLMAP's test of its inliers)."""
    a = np.column_stack([(za - c) / f, np.ones(len(za))])
    b = np.column_stack([(zb - c) / f, np.ones(len(zb))])
    Ea, Eb = a @ E.T, b @ E
    algebraic = np.sum(b * Ea, axis=1)
    squared = algebraic ** 2 / np.maximum(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Eb[:, 0] ** 2 + Eb[:, 1] ** 2, 1e-300)
    return squared <= (MAX_ERROR / f) ** 2


def _rows_of(tracks, k, points):
    """The rows of view ``k``'s observations of ``points`` (each seen there once)."""
    rows = np.flatnonzero(tracks.view == k)
    order = np.argsort(tracks.point[rows])
    return rows[order][np.searchsorted(tracks.point[rows][order], points)]


def _pair_state(tracks, a, b, pose, inliers, f, c) -> PinholeStart:
    K, N = tracks.n_views, tracks.n_points
    R, t = np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3))
    R[b], t[b] = pose
    registered = np.zeros(K, dtype=bool)
    registered[[a, b]] = True
    state = PinholeStart(np.zeros((N, 3)), _cameras(R, t, f, c), np.zeros(N, dtype=bool), registered,
                         np.zeros(len(tracks.view), dtype=bool), np.zeros(N, dtype=bool))
    candidates = np.zeros(N, dtype=bool)
    candidates[inliers] = True
    _triangulate(tracks, state, candidates)
    return state


def _rays(tracks, state, points):
    rows = np.flatnonzero(np.isin(tracks.point, points) & state.registered[tracks.view])
    rays, lines = ray_directions(state.cameras.projection_matrices(), state.X, tracks.view[rows],
                                 tracks.point[rows])
    return rays, tracks.point[rows], lines


def _triangulate(tracks, state, candidates=None) -> None:
    """Place the unplaced points (or ``candidates``) seen in 2 registered views
    or more, where their rays meet widely and they reproject within MAX_ERROR px."""
    N = tracks.n_points
    rows = state.registered[tracks.view]
    counts = np.bincount(tracks.point[rows], minlength=N)
    wanted = (counts >= 2) & (~state.placed if candidates is None else candidates)
    rows &= wanted[tracks.point]
    if not rows.any():
        return
    P = state.cameras.projection_matrices()
    A, b = dlt_rows(P, tracks.view[rows], tracks.z[rows])
    X = state.X.copy()
    # the wanted points alone (each resection's few, not every track: 100
    # photos, 0.6 s of pseudo-inverses of 3x3 blocks)
    ids = np.flatnonzero(wanted)
    X[ids] = least_squares_points(A, b, np.searchsorted(ids, tracks.point[rows]), len(ids))
    error = np.linalg.norm(state.cameras.project(X, tracks.view[rows], tracks.point[rows]) - tracks.z[rows],
                           axis=1)
    good = np.ones(N, dtype=bool)
    bad_points = tracks.point[rows][~(error <= MAX_ERROR)]  # nan: behind a camera
    good[bad_points] = False
    wide = widest_angles(_bearings(state.cameras, tracks, rows), tracks.point[rows], N) >= MIN_RAY_ANGLE
    new = wanted & good & wide
    state.X[new] = X[new]
    state.placed |= new
    # a narrow point's linear triangulation is no test of its matches: set aside, not suspect
    state.narrow = (state.narrow | (wanted & ~wide)) & ~state.placed
    state.kept |= rows & new[tracks.point]


def _bearings(cameras: Cameras, tracks, rows) -> np.ndarray:
    """Unit directions, in the world, of the rays through the observations
    ``rows``: the angle between two of them is the point's triangulation angle
    wherever its linear triangulation lands (far out, that place is noise)."""
    n = (tracks.z[rows] - cameras.principal_point) / cameras.focal()[tracks.view[rows], None]
    rays = np.einsum("tji,tj->ti", cameras.current_rotations()[tracks.view[rows]],
                     np.column_stack([n, np.ones(len(n))]))
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _next_view(tracks, state, failed) -> int | None:
    rows = state.placed[tracks.point] & ~state.registered[tracks.view]
    counts = np.bincount(tracks.view[rows], minlength=tracks.n_views).astype(float)
    counts[list(failed)] = 0
    k = int(np.argmax(counts))
    return k if counts[k] >= MIN_RESECTION else None


def _resect(tracks, state, k, box, seed) -> bool:
    rows = np.flatnonzero((tracks.view == k) & state.placed[tracks.point])
    camera = _colmap_camera(float(state.cameras.focal()[0]), state.cameras.principal_point, box)
    found = colmap.absolute_pose(tracks.z[rows], state.X[tracks.point[rows]], camera, max_error=MAX_ERROR,
                                 seed=seed, trials=RANSAC_TRIALS)
    if found is None or found[3] < MIN_RESECTION:
        return False
    cameras = state.cameras.reanchored()
    cameras.rotations[k], cameras.params[k, 3:6], inliers, _ = found
    state.cameras = cameras
    state.registered[k] = True
    state.kept[rows[inliers]] = True
    return True


def _adjust(tracks, state) -> None:
    """Bundle adjustment of the registered views and placed points, then
    COLMAP's filter: observations beyond MAX_ERROR px out, points left in
    fewer than 2 views unplaced."""
    rows = state.kept & state.placed[tracks.point] & state.registered[tracks.view]
    # the registered views and placed points alone: the others' columns would
    # only widen the camera system (250 views: 12 of 17 s in its Cholesky)
    views, points = np.flatnonzero(state.registered), np.flatnonzero(state.placed)
    view_index, point_index = np.cumsum(state.registered) - 1, np.cumsum(state.placed) - 1
    sub = Tracks(view_index[tracks.view[rows]], point_index[tracks.point[rows]], tracks.z[rows],
                 len(points), len(views))
    fit = adjust(state.X[points], state.cameras.take(views), sub, ROUND_OPTIONS)
    if np.all(np.isfinite(fit.X)) and np.isfinite(fit.history[-1]):
        state.X = state.X.copy()
        state.X[points] = fit.X
        state.cameras = state.cameras.put(views, fit.cameras)
    error = np.linalg.norm(state.cameras.project(state.X, tracks.view, tracks.point) - tracks.z, axis=1)
    state.kept &= error <= MAX_ERROR
    counts = np.bincount(tracks.point[state.kept & state.registered[tracks.view]], minlength=tracks.n_points)
    state.placed &= counts >= 2
    state.kept &= state.placed[tracks.point]
