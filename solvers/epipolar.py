"""Wrong matches found before any 3D fit: two-view affine epipolar consensus.

A wrong match dominates a least-squares fit (dino, 3% of the observations
swapped for another point's: 80 residuals of ~150 px outweigh 2,500 of ~1 px
a thousand times in squared error), so no fit that starts from least squares
can be trusted to point at it. Two views alone can: under an affine camera the
matches (z_k, z_j) of two views lie on a hyperplane of R^4 (the affine
epipolar constraint, Hartley & Zisserman section 14.2), whatever the 3D shape,
and a robust fit of that hyperplane (RANSAC, MSAC scoring, then total least
squares on the inliers) flags the pairs far from it. An observation is taken
for a wrong match when most of the view pairs that test it flag it: a wrong
match in view k is far from the hyperplane of every pair (k, j), a right one
only in the pair with the wrong one.

When two views look along nearly the same direction (a hand-held video
moving sideways), the matches lie close to a plane inside that hyperplane
(z_j ~ A z_k + t), and a wrong match can hide along the hyperplane's third
direction: its depth under the other view's camera absorbs it. So each pair
is also tested against its robust 2D affine subspace, in units of that fit's
own sigma; for views far apart that sigma is the parallax, and the test is
mute. (backyard, 3% wrong matches: 35 of 72 found by the hyperplane alone, 69
with both; 0 and 1 of the clean observations flagged.)

Perspective views are near-affine over two views at a time, and the
threshold is in robust sigmas of each pair's own residuals, so their misfit
is rarely flagged (and a flag is only a suspicion: the fit takes back what
it explains); a wrong match along its epipolar line escapes, and is left to
the peeling after the fit (:func:`.bundle._without_outliers`).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix

SIGMAS = 10.0  # a pair's residual beyond this many of its robust sigmas is flagged
MIN_COMMON = 12  # points two views must share to be tested together
PARTNERS = 8  # views tested with each view: those sharing the most points with it
TRIALS = 100  # RANSAC samples per pair
_SCORED = 2000  # matches a sample is scored on (all of them for smaller pairs)
_MAD = 0.6745  # median |r| / sigma for Gaussian r


def epipolar_outliers(view: np.ndarray, point: np.ndarray, z: np.ndarray, n_views: int,
                      n_points: int, *, sigmas: float = SIGMAS, floor: float = 0.0,
                      seed: int = 0) -> np.ndarray:
    """(T,) bool: the observations that most of their view pairs flag as off the
    pair's affine epipolar hyperplane, by more than ``sigmas`` robust sigmas
    (and more than ``floor`` pixels). Observations tested by fewer than two
    pairs (a point seen twice) are never flagged."""
    by_view = np.split(np.argsort(view, kind="stable"),
                       np.cumsum(np.bincount(view, minlength=n_views))[:-1])
    flags, tests = np.zeros(len(view)), np.zeros(len(view))
    rng = np.random.default_rng(seed)
    for k, j in _pairs(view, point, n_views, n_points):
        # the observations of the points both views see
        _, ia, ib = np.intersect1d(point[by_view[k]], point[by_view[j]], return_indices=True)
        ta, tb = by_view[k][ia], by_view[j][ib]
        q = np.hstack([z[ta], z[tb]])
        far = off_affine_subspace(q, sigmas=sigmas, floor=floor, rng=rng) \
            | off_affine_subspace(q, sigmas=sigmas, floor=floor, rng=rng, dim=2)
        np.add.at(flags, ta, far)
        np.add.at(flags, tb, far)
        np.add.at(tests, ta, 1)
        np.add.at(tests, tb, 1)
    return (tests >= 2) & (flags > tests / 2)


def _pairs(view, point, n_views, n_points):
    """The view pairs tested: each view with the PARTNERS views sharing the most
    points with it, if they share at least MIN_COMMON."""
    seen = csr_matrix((np.ones(len(view)), (view, point)), shape=(n_views, n_points))
    common = (seen @ seen.T).toarray()
    np.fill_diagonal(common, 0)
    best = np.argsort(-common, axis=1, kind="stable")[:, :PARTNERS]
    pairs = {(min(k, j), max(k, j)) for k in range(n_views) for j in best[k]
             if common[k, j] >= MIN_COMMON}
    return sorted(pairs)


def off_affine_subspace(q: np.ndarray, *, sigmas: float = SIGMAS, floor: float = 0.0,
                        rng=None, dim: int = 3) -> np.ndarray:
    """(n,) bool: the rows of q (n, d) far from the robust ``dim``-dimensional affine
    subspace through them (default 3).

    Under affine cameras the stacked images of a point in m views lie on a 3D
    affine subspace of R^2m (two views: a hyperplane of R^4), and so do the
    pairs (x_i, z_i) of one view's points and images in R^5: one test serves
    wrong matches between views, in a seed of views and in a resection. RANSAC
    over samples of dim + 1 rows, MSAC scoring with each sample's own robust scale,
    then total least squares on the rows near the best; a row is far beyond
    ``sigmas`` robust sigmas and ``floor`` (in q's units).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    n = len(q)
    centre = np.median(q, axis=0)
    scale = np.median(np.abs(q - centre)) or 1.0
    q = (q - centre) / scale  # conditioned: distances of O(1)
    scored = q if n <= _SCORED else q[rng.choice(n, _SCORED, replace=False)]
    samples = q[rng.integers(0, n, size=(TRIALS, dim + 1))]  # a repeated row gives a bad fit: harmless
    means = samples.mean(axis=1)
    # distances are measured through the complement
    normals = _least_spread(samples - means[:, None], dim)  # (S, d - dim, d)
    along = np.einsum("nd,scd->snc", scored, normals) - np.einsum("sd,scd->sc", means, normals)[:, None]
    distance = np.linalg.norm(along, axis=2).T  # (n', S)
    sigma = np.maximum(np.median(distance, axis=0) / _MAD, 1e-12)
    cost = np.minimum(distance / sigma, sigmas).sum(axis=0) + len(scored) * np.log(sigma)
    best = int(np.argmin(cost))
    mean, normal = means[best], normals[best]
    for _ in range(3):  # total least squares on the rows close to it
        distance = np.linalg.norm((q - mean) @ normal.T, axis=1)
        near = distance <= sigmas * max(np.median(distance) / _MAD, 1e-12)
        if near.sum() < 5:
            break
        mean = q[near].mean(axis=0)
        normal = _least_spread(q[near] - mean, dim)
    distance = np.linalg.norm((q - mean) @ normal.T, axis=1)
    sigma = np.median(distance) / _MAD
    return (distance > sigmas * sigma) & (distance * scale > floor)


def _least_spread(centred: np.ndarray, dim: int) -> np.ndarray:
    """(..., d - dim, d): the directions of least spread of centred rows (..., n, d),
    the eigenvectors of their scatter (half the time of an SVD, and d x d
    whatever n)."""
    scatter = np.swapaxes(centred, -1, -2) @ centred
    return np.swapaxes(np.linalg.eigh(scatter)[1][..., :centred.shape[-1] - dim], -1, -2)
