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
the peeling after the fit (:func:`.outliers.without_outliers`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.sparse import csr_matrix

from mpe3d.solvers.sfm.epipolar_kernels import eight_point_samples, sampson_costs, subspace_costs
from mpe3d.solvers.threads import map_drawn, map_in_order

SIGMAS = 10.0  # a pair's residual beyond this many of its robust sigmas is flagged
MIN_COMMON = 12  # points two views must share to be tested together
# matches a pair needs for its fundamental matrix (7 degrees of freedom) to
# vote: with fewer, RANSAC's 8-point samples of noisy keypoints from views
# looking nearly the same way (backyard: 14-44 a frame) fit clean ones badly
MIN_FUNDAMENTAL = 50
PARTNERS = 8  # views tested with each view: those sharing the most points with it
TRIALS = 100  # RANSAC samples per pair
_SCORED = 2000  # matches a sample is scored on (all of them for smaller pairs)
_DRAWN = 256  # the random numbers are drawn as if pairs with more matches stood alone
_STACK = 128  # arrays per stack: a fixed split, so the threads share the work
_MAD = 0.6745  # median |r| / sigma for Gaussian r


class TwoViews(NamedTuple):
    """What two views at a time tell before any 3D fit.

    ``noise`` and ``affine`` are robust sigmas in pixels, each the median over
    the pairs with matches enough for a fundamental matrix (NaN when none
    has): of the distances to the pair's epipolar geometry, which holds for
    pinholes and affine cameras alike (the keypoints' noise), and to its
    affine epipolar hyperplane (the noise, plus the perspective no affine
    camera explains). Both estimate the noise of each coordinate: a match's
    distance to either is one normal variable of it.
    """

    flagged: np.ndarray  # (T,) bool: likely wrong matches
    noise: float
    affine: float


def epipolar_outliers(view: np.ndarray, point: np.ndarray, z: np.ndarray, n_views: int,
                      n_points: int, *, sigmas: float = SIGMAS, floor: float = 0.0,
                      seed: int = 0) -> np.ndarray:
    """(T,) bool: the observations that most of their view pairs flag as off the
    pair's affine epipolar hyperplane, or off its robust plane in it, by more
    than ``sigmas`` robust sigmas (and more than ``floor`` pixels). Observations tested by fewer than two
    pairs (a point seen twice) are never flagged."""
    return two_view_tests(view, point, z, n_views, n_points, sigmas=sigmas, floor=floor, seed=seed).flagged


def two_view_tests(view: np.ndarray, point: np.ndarray, z: np.ndarray, n_views: int,
                   n_points: int, *, sigmas: float = SIGMAS, floor: float = 0.0,
                   seed: int = 0, partners: int = PARTNERS) -> TwoViews:
    """:func:`epipolar_outliers`' flags and the two noise levels of
    :class:`TwoViews`, from each view and its ``partners`` views sharing the
    most points."""
    by_view = np.split(np.argsort(view, kind="stable"),
                       np.cumsum(np.bincount(view, minlength=n_views))[:-1])
    tested = []
    for k, j in _pairs(view, point, n_views, n_points, partners):
        # the observations of the points both views see
        _, ia, ib = np.intersect1d(point[by_view[k]], point[by_view[j]], return_indices=True)
        tested.append((by_view[k][ia], by_view[j][ib]))
    matches = [np.hstack([z[ta], z[tb]]) for ta, tb in tested]
    rng = np.random.default_rng(seed)
    (hyperplane, affine), (plane, _) = (_off_affine_subspaces_scaled(matches, sigmas, floor, rng, dim)
                                        for dim in (3, 2))
    far = [a | b for a, b in zip(hyperplane, plane)]
    # a pinhole pair's wrong match can sit on the affine hyperplane and off the
    # true epipolar lines: where the pair has matches enough to fix its
    # fundamental matrix, that test votes too
    epipolar, noise = _off_epipolar_lines_each(matches, sigmas, floor, rng)
    far = [f if e is None else f | e for f, e in zip(far, epipolar)]
    flags, tests = np.zeros(len(view)), np.zeros(len(view))
    for (ta, tb), f in zip(tested, far):
        for t in (ta, tb):
            np.add.at(flags, t, f)
            np.add.at(tests, t, 1)
    flagged = (tests >= 2) & (flags > tests / 2)
    fundamental = [i for i, e in enumerate(epipolar) if e is not None]
    return TwoViews(flagged | _alone_and_off(tested, epipolar, tests),
                    float(np.median([noise[i] for i in fundamental])) if fundamental else float("nan"),
                    float(np.median([affine[i] for i in fundamental])) if fundamental else float("nan"))


def _alone_and_off(tested, epipolar, tests) -> np.ndarray:
    """(T,) bool: the observations that a single pair tests (a point seen in two
    views) and that pair's epipolar geometry puts off their epipolar lines.

    No vote can tell which of a two-view track's observations is the wrong
    one, but the pair can tell that one is: both are flagged, and the point
    goes unplaced unless the fit takes it back. The pair's test is the
    fundamental matrix's (:func:`off_epipolar_lines`), which holds for
    pinholes and affine cameras alike, so a pinhole's perspective is no misfit.
    ``epipolar`` holds each pair's result of that test, None where the pair has
    too few matches for it: the vote's own, not a second RANSAC (which had
    doubled the test's time on 250 views, 23 s, for other random samples of the
    same fit).
    """
    alone = np.zeros(len(tests), dtype=bool)
    for (ta, tb), off in zip(tested, epipolar):
        single = (tests[ta] == 1) | (tests[tb] == 1)
        if not single.any() or off is None:
            continue
        off = off & single
        alone[ta[off & (tests[ta] == 1)]] = True
        alone[tb[off & (tests[tb] == 1)]] = True
    return alone


def _normalising(points: np.ndarray) -> np.ndarray:
    """Hartley's conditioning: the 3x3 map taking ``points`` to mean 0 and mean
    distance sqrt(2)."""
    centre = points.mean(axis=0)
    scale = np.sqrt(2) / max(float(np.mean(np.linalg.norm(points - centre, axis=1))), 1e-300)
    return np.array([[scale, 0, -scale * centre[0]], [0, scale, -scale * centre[1]], [0, 0, 1]])


def _fundamentals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rank-2 fundamental matrices b^T F a = 0 by the eight-point
    method, from homogeneous (..., n, 3) rows: the fit to the matches near
    RANSAC's best, and its rank-deficient samples
    (:func:`~mpe3d.solvers.kernels.eight_point_samples` does the others)."""
    A = (b[..., :, :, None] * a[..., :, None, :]).reshape(*a.shape[:-1], 9)
    # the null vector is the last row of V^T: a sample of 8 needs the full 9 x 9,
    # a fit to all n >= 9 matches not the n x n U a full SVD also builds (3 s at
    # 10,000 matches, 2 ms without; V^T is the same bits)
    F = np.linalg.svd(A, full_matrices=A.shape[-2] < 9)[2][..., -1, :].reshape(*a.shape[:-2], 3, 3)
    U, S, Vt = np.linalg.svd(F)
    S[..., 2] = 0.0
    return U @ (S[..., :, None] * Vt)


def _sampson(F: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., n) Sampson distances of the matches (a, b) to F (first-order geometric error)."""
    Fa = a @ np.swapaxes(F, -1, -2)  # (..., n, 3): the epipolar lines in b's view
    Fb = b @ F  # and in a's
    algebraic = np.sum(b * Fa, axis=-1)
    gradient = Fa[..., 0] ** 2 + Fa[..., 1] ** 2 + Fb[..., 0] ** 2 + Fb[..., 1] ** 2
    return np.abs(algebraic) / np.sqrt(np.maximum(gradient, 1e-300))


def _off_epipolar_lines_each(matches, sigmas, floor, rng) -> tuple[list, list]:
    """:func:`off_epipolar_lines` of each pair with MIN_FUNDAMENTAL matches or
    more (None for the others), on :func:`~mpe3d.solvers.threads.count`
    threads, each pair's random numbers drawn in the pairs' order; and each
    tested pair's robust sigma in pixels (NaN for the others)."""
    tested = [i for i, q in enumerate(matches) if len(q) >= MIN_FUNDAMENTAL]
    off = map_drawn(lambda q: _epipolar_draws(len(q), rng, 2 * TRIALS),
                    lambda q, draws: _off_epipolar_lines(q, draws, sigmas, floor), [matches[i] for i in tested])
    epipolar, noise = [None] * len(matches), [float("nan")] * len(matches)
    for i, (f, sigma) in zip(tested, off):
        epipolar[i], noise[i] = f, sigma
    return epipolar, noise


def _epipolar_draws(n: int, rng, trials: int):
    """The random numbers :func:`off_epipolar_lines` uses for n matches, in
    the order it has always drawn them: the matches scored, then the
    samples' keys."""
    scored = np.arange(n) if n <= _SCORED else np.sort(rng.choice(n, _SCORED, replace=False))
    return scored, rng.random((trials, len(scored)))


def off_epipolar_lines(q: np.ndarray, *, sigmas: float = SIGMAS, floor: float = 0.0,
                       rng=None, trials: int = 2 * TRIALS) -> np.ndarray:
    """(n,) bool: the matches (rows of q: x_a, y_a, x_b, y_b) off the two views'
    robust epipolar geometry (Hartley & Zisserman sections 11.1-11.4): RANSAC
    over samples of 8 (the normalised eight-point method), MSAC scoring with
    each sample's own robust scale (samples and scores among _SCORED matches
    at most, drawn at random), then the eight-point fit to the matches
    near the best, twice; a match is off beyond ``sigmas`` robust sigmas of
    the Sampson distance and ``floor`` pixels."""
    rng = np.random.default_rng(0) if rng is None else rng
    return _off_epipolar_lines(q, _epipolar_draws(len(q), rng, trials), sigmas, floor)[0]


def _off_epipolar_lines(q, draws, sigmas, floor) -> tuple[np.ndarray, float]:
    """:func:`off_epipolar_lines` with its random numbers drawn (``draws``),
    and the robust sigma of the distances in pixels."""
    n = len(q)
    Ta, Tb = _normalising(q[:, :2]), _normalising(q[:, 2:])
    a = np.c_[q[:, :2], np.ones(n)] @ Ta.T
    b = np.c_[q[:, 2:], np.ones(n)] @ Tb.T
    # samples drawn and scored among _SCORED matches at most, as the affine test
    # does: a pair of a million-point scene shares 375,000 (a trials x n array
    # each is 600 MB); the fits to the matches near the best use them all
    scored, keys = draws
    a_scored, b_scored = a[scored], b[scored]
    F, degenerate = eight_point_samples(a_scored, b_scored, keys)
    if degenerate.any():  # a null plane: SVD's vector in it, as before the kernel
        picks = np.argsort(keys[degenerate], axis=1)[:, :8]
        F[degenerate] = _fundamentals(a_scored[picks], b_scored[picks])
    capped, sigma = sampson_costs(F, a_scored, b_scored, _MAD, float(sigmas))
    best = F[np.argmin(capped + len(scored) * np.log(sigma))]
    for _ in range(2):
        distance = _sampson(best, a, b)
        near = distance <= sigmas * max(np.median(distance) / _MAD, 1e-12)
        if near.sum() < 8:
            break
        best = _fundamentals(a[near], b[near])
    distance = _sampson(best, a, b)
    sigma = np.median(distance) / _MAD
    unit = 0.5 * (Ta[0, 0] + Tb[0, 0])  # the conditioning's scale, undone
    return (distance > sigmas * sigma) & (distance / unit > floor), float(sigma / unit)


def _pairs(view, point, n_views, n_points, partners: int = PARTNERS):
    """The view pairs tested: each view with the ``partners`` views sharing the
    most points with it, if they share at least MIN_COMMON."""
    seen = csr_matrix((np.ones(len(view)), (view, point)), shape=(n_views, n_points))
    common = (seen @ seen.T).toarray()
    np.fill_diagonal(common, 0)
    best = np.argsort(-common, axis=1, kind="stable")[:, :partners]
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
    over samples of dim + 1 rows, MSAC scoring with each sample's own robust
    scale, then total least squares on the rows near the best; a row is far
    beyond ``sigmas`` robust sigmas and ``floor`` (in q's units).
    """
    return off_affine_subspaces([q], sigmas=sigmas, floor=floor, rng=rng, dim=dim)[0]


def off_affine_subspaces(qs: list, *, sigmas: float = SIGMAS, floor: float = 0.0,
                         rng=None, dim: int = 3) -> list:
    """:func:`off_affine_subspace` of each (n_b, d) array of ``qs`` at once: the
    arrays are padded to (B, n, d) stacks of like sizes, because a two-view
    test of a long sequence is hundreds of pairs of a few hundred matches at
    most, where numpy's per-call cost is most of the work (backyard: 1.0 s one
    pair at a time; 250 views x 3,000 points, 1,270 pairs of 228-319: 4.3 s
    with those over 256 alone, 2.2 s stacked)."""
    rng = np.random.default_rng(0) if rng is None else rng
    return _off_affine_subspaces_scaled(qs, sigmas, floor, rng, dim)[0]


def _off_affine_subspaces_scaled(qs: list, sigmas, floor, rng, dim) -> tuple[list, list]:
    """:func:`off_affine_subspaces` and each array's robust sigma in q's units."""
    if not qs:  # views sharing too few points for any pair to be tested
        return [], []
    sizes = np.array([len(q) for q in qs])
    draws = [None] * len(qs)
    for members in _stacks(sizes, _DRAWN, len(qs)):  # the order the numbers have always come in
        chosen, fractions = _affine_draws(sizes[members], rng, dim)
        for i, rows, sample in zip(members, chosen, fractions):
            draws[i] = rows, sample
    return _off_affine_stacked(qs, draws, sigmas, floor, dim)


def off_affine_subspace_each(qs: list, *, sigmas: float = SIGMAS, floor: float = 0.0,
                             seed: int = 0, dim: int = 3) -> list:
    """[off_affine_subspace(q, rng=np.random.default_rng(seed)) for q in qs]:
    each array gets the samples that call gives it, and the arrays are tested
    in stacks as :func:`off_affine_subspaces` does (250 resections of ~550
    rows each: 0.9 s one at a time). A padded stack may move a distance's
    last bit; the flags were those of the single calls on every set tried."""
    draws = []
    for q in qs:
        chosen, fractions = _affine_draws([len(q)], np.random.default_rng(seed), dim)
        draws.append((chosen[0], fractions[0]))
    return _off_affine_stacked(qs, draws, sigmas, floor, dim)[0]


def _off_affine_stacked(qs, draws, sigmas, floor, dim) -> tuple[list, list]:
    """The tests of :func:`off_affine_subspaces`, each array's random numbers
    drawn (``draws``), in stacks of like sizes on the solver's threads; and
    each array's robust sigma in its units."""
    sizes = np.array([len(q) for q in qs])
    groups = _stacks(sizes, _SCORED, _STACK)
    tested = map_in_order(lambda members: _off_affine_subspaces(
        [qs[i] for i in members], [draws[i] for i in members], sigmas, floor, dim), groups)
    far, spread = [None] * len(qs), [None] * len(qs)
    for members, (result, sigma) in zip(groups, tested):
        for i, f, s in zip(members, result, sigma):
            far[i], spread[i] = f, float(s)
    return far, spread


def _stacks(sizes: np.ndarray, alone: int, most: int) -> list:
    """Index arrays of the arrays stacked together: those of up to ``alone`` rows
    by their power of two (padded to at most twice), ``most`` to a stack, the
    larger ones each alone (numpy's overhead is nothing there, and unpadded
    medians partition). Stacks of single arrays come first, the last array's
    first, as they always have."""
    buckets = np.ceil(np.log2(np.maximum(sizes, 1))).astype(int)
    buckets = np.where(sizes > alone, -1 - np.arange(len(sizes)), buckets)
    groups = [np.flatnonzero(buckets == bucket) for bucket in np.unique(buckets)]
    return [group[start:start + most] for group in groups for start in range(0, len(group), most)]


def _affine_draws(sizes, rng, dim: int):
    """The random numbers :func:`_off_affine_subspaces` uses for arrays of
    ``sizes`` rows: the rows each array is scored on (None: all), then each
    sample's rows (as fractions of the array's length), (B, TRIALS, dim + 1)."""
    scored = [rng.choice(n, _SCORED, replace=False) if n > _SCORED else None for n in sizes]
    return scored, rng.random((len(sizes), TRIALS, dim + 1))


def _off_affine_subspaces(qs, draws, sigmas, floor, dim) -> list:
    """:func:`off_affine_subspaces` of one stack, each array's random numbers
    drawn (``draws``: its scored rows and its samples' fractions)."""
    Q, valid = _padded(qs)
    counts = valid.sum(axis=1)
    centre = _masked_median(Q, valid[:, :, None], axis=1)
    scale = _masked_median(np.abs(Q - centre[:, None]).reshape(len(Q), -1),
                           np.repeat(valid, Q.shape[2], axis=1), axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    Q = (Q - centre[:, None]) / scale[:, None, None]  # conditioned: distances of O(1)
    chosen = [rows for rows, _ in draws]
    fractions = np.stack([sample for _, sample in draws])
    scored, scored_valid = _padded([q if rows is None else q[rows]
                                    for q, rows in zip(_unpadded(Q, counts), chosen)])
    # a repeated row gives a bad fit: harmless
    picks = (fractions * counts[:, None, None]).astype(int)
    samples = np.take_along_axis(Q[:, None], picks[..., None], axis=2)  # (B, S, dim + 1, d)
    means = samples.mean(axis=2)
    normals = _least_spread(samples - means[:, :, None], dim)  # (B, S, d - dim, d)
    counts_scored = scored_valid.sum(axis=1)
    capped, sigma = subspace_costs(scored, counts_scored, means, np.ascontiguousarray(normals), _MAD,
                                   float(sigmas))
    best = np.argmin(capped + counts_scored[:, None] * np.log(sigma), axis=1)
    mean, normal = means[np.arange(len(Q)), best], normals[np.arange(len(Q)), best]
    for _ in range(3):  # total least squares on the rows close to it
        distance = _distances(Q, mean, normal)
        sigma = np.maximum(_masked_median(distance, valid, axis=1) / _MAD, 1e-12)
        near = valid & (distance <= sigmas * sigma[:, None])
        refit = near.sum(axis=1) >= 5  # too few near: keep the sample's fit
        weight = near[:, :, None].astype(float)
        centroid = (weight * Q).sum(axis=1) / np.maximum(weight.sum(axis=1), 1)
        tls = _least_spread(weight * (Q - centroid[:, None]), dim)
        mean = np.where(refit[:, None], centroid, mean)
        normal = np.where(refit[:, None, None], tls, normal)
    distance = _distances(Q, mean, normal)
    sigma = _masked_median(distance, valid, axis=1) / _MAD
    far = (distance > sigmas * sigma[:, None]) & (distance * scale[:, None] > floor)
    return _unpadded(far, counts), sigma * scale


def _padded(arrays):
    """(B, n_max, ...) zero-padded stack and its (B, n_max) mask of real rows."""
    n = np.array([len(a) for a in arrays])
    stack = np.zeros((len(arrays), max(n.max(initial=0), 1)) + arrays[0].shape[1:])
    valid = np.arange(stack.shape[1]) < n[:, None]
    stack[valid] = np.concatenate(arrays)
    return stack, valid


def _unpadded(stack, counts):
    return [row[:c] for row, c in zip(stack, counts)]


def _masked_median(values, valid, axis):
    """The median along ``axis`` of the entries where ``valid`` (broadcast to values)."""
    valid = np.broadcast_to(valid, values.shape)
    if valid.all():
        return np.median(values, axis=axis)
    ordered = np.sort(np.where(valid, values, np.inf), axis=axis)
    n = valid.sum(axis=axis, keepdims=True)
    low = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0), axis=axis)
    high = np.take_along_axis(ordered, n // 2, axis=axis)
    return np.squeeze((low + high) / 2, axis=axis)


def _distances(Q, mean, normal):
    """(B, n): each row's distance to its stack's subspace (mean, complement)."""
    return np.linalg.norm(np.einsum("bnd,bcd->bnc", Q - mean[:, None], normal), axis=2)


def _least_spread(centred: np.ndarray, dim: int) -> np.ndarray:
    """(..., d - dim, d): the directions of least spread of centred rows (..., n, d),
    the eigenvectors of their scatter (half the time of an SVD, and d x d
    whatever n)."""
    scatter = np.swapaxes(centred, -1, -2) @ centred
    return np.swapaxes(np.linalg.eigh(scatter)[1][..., :centred.shape[-1] - dim], -1, -2)
