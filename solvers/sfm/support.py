"""What a bundle adjustment's fit rests on: the informative observations
(a point seen at least twice), the placed points, the points whose geometry is
too weak to trust (rays under MIN_RAY_ANGLE apart, or farther than FAR_FACTOR
times the median radius), and the per-view means those steps share."""

from __future__ import annotations

import numpy as np

from mpe3d.solvers.linalg import sum_by
from mpe3d.solvers.sfm.cameras import (
    Cameras,
)
from mpe3d.solvers.sfm.tracks import Tracks
from mpe3d.solvers.sfm.triangulation import (
    ray_directions,
    widest_angles,
)

# A cloud longer than this many times its second extent has not been determined
# along its long axis: the views leave its depth free.
ELONGATION = 20.0
# Weak geometry: a point whose kept rays all meet under MIN_RAY_ANGLE degrees
# (COLMAP's triangulator refuses these too), or that lies farther from the
# cloud's median than FAR_FACTOR times the median distance of the cloud's
# points to it, has no depth the views fix: it is left unplaced, like a point
# seen once. On COLMAP's tracks of 250 photos one such point, its rays a
# fraction of a degree apart, stood 7e8 away and set the whole cloud's mean CD.
MIN_RAY_ANGLE = 1.5
FAR_FACTOR = 100.0


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


def informative(tracks: Tracks, kept: np.ndarray) -> np.ndarray:
    """The observations ``kept`` less those of points kept in fewer than 2 views: a point
    seen once fits any camera, so it says nothing about them (it is placed on
    its ray afterwards)."""
    counts = np.bincount(tracks.point[kept], minlength=tracks.n_points)
    return kept & (counts[tracks.point] >= 2)


def placed_points(tracks, used) -> np.ndarray:
    """(N,) bool: the points the solve placed (seen in 2 or more views)."""
    return np.bincount(tracks.point[used], minlength=tracks.n_points) >= 2


def weak_points(fit, tracks, kept):
    """(N,) bool masks ``weak``, ``placed``, ``narrow`` and ``far``: the points
    of weak geometry (:func:`weak_geometry`) under ``fit`` with the ``kept``
    observations, and what they are made of. ``weak`` is none when they are
    over half the placed points: then no depth is fixed, which is said, not
    solved."""
    placed = placed_points(tracks, informative(tracks, kept))
    narrow, far = weak_geometry(*fit[:2], tracks, kept, placed)
    weak = narrow | far
    return (weak if weak.sum() <= placed.sum() / 2 else np.zeros_like(weak)), placed, narrow, far


def mean_by_view(values, tracks):
    counts = np.maximum(np.bincount(tracks.view, minlength=tracks.n_views), 1)
    return sum_by(tracks.view, values, tracks.n_views) / counts[:, None]

