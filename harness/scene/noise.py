"""The paper's two noise regimes (Section "Robustness of the Algorithm").

What the paper leaves vague, and what we do:

* ``d``, "the diameter of the point cloud", is the largest distance between
  two of the N sampled 3D points.
* Distance noise picks its round(q n_k) rows independently in each view
  (``noise.rows=per_view``), or round(q N) points once, whose rows are noisy
  in every view that sees them (``noise.rows=shared``, the authors' code). Noise with variance
  p d (sigma = sqrt(p d)) is added to every entry of those rows; negatives are
  clipped to 0; the matrix is made symmetric by averaging it with its
  transpose, so an entry in one noisy row carries variance p d / 4 and an entry
  where two noisy rows cross carries p d / 2; the diagonal is zeroed.
* Correspondence noise picks round(q N) points once and, for each, another
  point chosen uniformly among those within p d of it in 3D (a point with no
  other point that close keeps its own position, and is not counted as
  moved). By default (``noise.views=one``, the paper's text and the authors'
  code) the wrong match is made in one view of the point, chosen uniformly
  among those that see it: its observation there is the other point's. With
  ``noise.views=all`` it is made in every view that sees it; the views then
  agree on a consistent, wrong cloud that no method can detect.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.distance import pdist


def diameter(points: np.ndarray) -> float:
    """The largest pairwise distance, through the convex hull when it is cheaper."""
    candidates = points
    if len(points) > 64:
        try:
            candidates = points[ConvexHull(points).vertices]
        except Exception:  # flat or degenerate clouds: fall back to all points
            candidates = points
    return float(pdist(candidates).max()) if len(candidates) > 1 else 0.0


def distance_noise(D: np.ndarray, fraction: float, amplitude: float, d: float,
                   rng: np.random.Generator, rows: np.ndarray | None = None) -> np.ndarray:
    """Gaussian noise N(0, p d) on round(q n) random rows of one view's distances,
    or on the given ``rows`` (``noise.rows=shared``: one set of points for all views)."""
    n = len(D)
    if rows is None:
        rows = rng.choice(n, size=int(round(fraction * n)), replace=False)
    noisy = D.copy()
    noisy[rows] += rng.normal(0.0, np.sqrt(amplitude * d), size=(len(rows), n))
    np.maximum(noisy, 0.0, out=noisy)
    noisy = 0.5 * (noisy + noisy.T)
    np.fill_diagonal(noisy, 0.0)
    return noisy


def correspondence_noise(points: np.ndarray, fraction: float, amplitude: float, d: float,
                         rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Observed 3D positions with round(q N) points replaced by a near neighbour's.

    Returns the positions every view projects and how many points really moved.
    """
    N = len(points)
    chosen = rng.choice(N, size=int(round(fraction * N)), replace=False)
    observed = points.copy()
    if len(chosen) == 0 or amplitude * d <= 0:
        return observed, 0
    tree = cKDTree(points)
    moved = 0
    for i, near in zip(chosen, tree.query_ball_point(points[chosen], r=amplitude * d)):
        others = [j for j in near if j != i]
        if others:
            observed[i] = points[others[rng.integers(len(others))]]
            moved += 1
    return observed, moved


def one_view_each(moved: np.ndarray, visible: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(K, N) bool: for each ``moved`` point, one of the views that see it, uniformly."""
    where = np.zeros_like(visible)
    for i in np.flatnonzero(moved & visible.any(axis=0)):
        views = np.flatnonzero(visible[:, i])
        where[views[rng.integers(len(views))], i] = True
    return where
