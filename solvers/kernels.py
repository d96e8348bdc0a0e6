"""Compiled passes: the 3DMPE stress (paper Eq. 1) one view at a time or all
dense views in one call (:func:`l2_views`), SMACOF's
Guttman transform, placing one point against anchors, the affine
factorisation's alternating least squares, bundle adjustment's per-observation
blocks (Jacobians, J^T w J, U^-1/2 W) and the Schur term of its reduced
camera system, and RANSAC's eight-point samples and scores in the two-view
tests of wrong matches.

For each pair i < j of a view the stress kernel forms the image distance
e_ij = ||y_i - y_j||, the residual r_ij = D_ij - e_ij, its weight
w_ij = a_i a_j (the visibility of Eq. 1 taken into [0, 1]) and minibatch bit,
the loss rho(r) and phi(r) = rho'(r) / 2, and adds both rows' gradient terms

    dS/dy_i += -2 w phi(r) (y_i - y_j) / e,   dS/dy_j -= the same,

so that no n x n temporary is ever made: the input distances are read once.
(The kernels sum the terms without the factor 2 and ``view_stress`` doubles
the sums, which is exact.) Row i's pairs are passed as slices [i + 1:] of
the view's arrays, indexed from 0: the compiler then proves every index
non-negative and turns the loop, row j's updates included, into 8-wide
vector square roots and divisions (AVX-512 here), about 7x the scalar loop
(``benchmarks/stress_kernel.py`` checks the packed instructions are there).
The loops are serial and in a fixed order; ``reassoc`` lets the compiler
split a row's sums into vector lanes, an order fixed when the kernel is
compiled, so a result is the same bits in every process, thread count and
backend on one machine. Numba caches the machine code on disk
(``cache=True``): a process loads it instead of compiling again, and
:func:`warm` does so before any solver's clock starts.

Optional inputs are passed as empty arrays rather than ``None``, so that each
kernel has one signature and one compilation.
"""

from __future__ import annotations

import functools

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from mpe3d.solvers.threads import even_split, map_in_order

# Loss codes, and the names a solver's ``loss`` option gives them.
L2, HUBER, SOFT_L1 = 0, 1, 2
LOSS_CODES = {"l2": L2, "huber": HUBER, "soft_l1": SOFT_L1}
# Floor on e in 1/e: keeps it finite for coincident images, where r e-terms cancel.
_E_FLOOR = 1e-12
# Reductions may be split into vector lanes (an order fixed at compile time) and
# a * b + c fused; no flag that changes a single operation's rounding or NaN/inf.
FASTMATH_FLAGS = {"reassoc", "nsz", "contract"}


@njit(cache=True, nogil=True, inline="always")
def _rho_phi(r, loss, scale):
    """rho(r), and phi(r) = rho'(r) / 2 as a numerator and a denominator, so
    that the caller's division by e takes phi's division along (soft-L1 pays
    one division a pair, not two). Branch-free: residuals on both sides of the
    scale come in any order."""
    if loss == L2:
        return r * r, r, 1.0
    if loss == HUBER:
        phi = min(max(r, -scale), scale)
        return phi * (2.0 * r - phi), phi, 1.0  # r^2 inside the scale, 2s|r| - s^2 beyond
    root = np.sqrt(1.0 + r * r * (1.0 / (scale * scale)))  # the division is hoisted out of the loop
    return 2.0 * scale * scale * (root - 1.0), r, root


@njit(cache=True, nogil=True, inline="always")
def _row(Di, y0, y1, Mi, alpha, xi, yi, ai, g0, g1, loss, scale, has_mask, has_alpha, want):
    """Row i's pairs (i, j > i), passed as the slices [i + 1:] of the view's
    arrays: their stress and the sums of w phi / (den e) (y_i - y_j), row i's
    gradient halved and negated; each term is added into row j's (g0, g1).
    Slices starting at 0 let the compiler prove every index non-negative and
    vectorise. Inlined with constant ``loss`` and flags, so that it drops the
    branches they decide; the caller's fastmath flags apply."""
    row = 0.0
    f0 = 0.0
    f1 = 0.0
    for t in range(Di.shape[0]):
        dx = xi - y0[t]
        dy = yi - y1[t]
        e = np.sqrt(dx * dx + dy * dy)
        r = Di[t] - e
        w = ai * alpha[t] if has_alpha else 1.0
        if has_mask:
            w = w if Mi[t] else 0.0
        if loss == SOFT_L1:  # in this form, not _rho_phi's, the compiler vectorises it
            root = np.sqrt(1.0 + r * r * (1.0 / (scale * scale)))
            row += w * (root - 1.0)
            b = w * r / max(root * e, _E_FLOOR)
        else:
            rho, phi, _ = _rho_phi(r, loss, scale)
            row += w * rho
            b = w * phi / max(e, _E_FLOOR)
        if want:
            f0 += b * dx
            f1 += b * dy
            g0[t] += b * dx
            g1[t] += b * dy
    if loss == SOFT_L1:
        row *= 2.0 * scale * scale
    return row, f0, f1


@njit(cache=True, nogil=True, inline="always")
def _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, has_mask, has_alpha, want):
    """The view's stress over its pairs i < j, and with ``want`` -1/2 dS/dy
    added into (g0, g1)."""
    total = 0.0
    no_mask = mask.ravel()[0:0]  # never read; an empty row without indexing an empty array
    for i in range(y0.shape[0] - 1):
        j = i + 1
        Mi = mask[i, j:] if has_mask else no_mask
        row, f0, f1 = _row(D[i, j:], y0[j:], y1[j:], Mi,
                           alpha[j:] if has_alpha else alpha, y0[i], y1[i],
                           alpha[i] if has_alpha else 1.0, g0[j:] if want else g0, g1[j:] if want else g1,
                           loss, scale, has_mask, has_alpha, want)
        total += row
        if want:
            g0[i] -= f0
            g1[i] -= f1
    return total


@njit(cache=True, nogil=True, inline="always")
def _dense_loss(D, y0, y1, mask, alpha, loss, scale, g0, g1):
    """One loss's specialisations, the flags as constants."""
    has_alpha, want = alpha.shape[0] > 0, g0.shape[0] > 0
    if mask.shape[0] > 0:  # SGD's minibatches (c < 1)
        return _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, True, has_alpha, want)
    if has_alpha:  # refine's rounds without the rejected observations
        if want:
            return _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, True, True)
        return _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, True, False)
    if want:  # every iteration of SGD and refine
        return _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, False, True)
    return _rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, False, False)


# One compiled function per loss: numba's compile time grows faster than the
# code it compiles, so three small functions compile far sooner than one.
@njit(cache=True, nogil=True, fastmath=FASTMATH_FLAGS)
def _dense_l2(D, y0, y1, mask, alpha, scale, g0, g1):
    return _dense_loss(D, y0, y1, mask, alpha, L2, scale, g0, g1)


@njit(cache=True, nogil=True, fastmath=FASTMATH_FLAGS)
def _dense_huber(D, y0, y1, mask, alpha, scale, g0, g1):
    return _dense_loss(D, y0, y1, mask, alpha, HUBER, scale, g0, g1)


@njit(cache=True, nogil=True, fastmath=FASTMATH_FLAGS)
def _dense_soft_l1(D, y0, y1, mask, alpha, scale, g0, g1):
    return _dense_loss(D, y0, y1, mask, alpha, SOFT_L1, scale, g0, g1)


DENSE_KERNELS = (_dense_l2, _dense_huber, _dense_soft_l1)  # by loss code


def dense_view(D, y0, y1, mask, alpha, loss, scale, g0, g1):
    """Stress of one view over its pairs i < j (D and ``mask`` read above the
    diagonal); adds -1/2 dS/dy into (g0, g1) unless they are empty. ``mask``
    (n x n booleans) and ``alpha`` (n weights) are skipped when empty."""
    return DENSE_KERNELS[loss](D, y0, y1, mask, alpha, scale, g0, g1)


@njit(cache=True, nogil=True)
def pair_view(i, j, d, y0, y1, mask, alpha, loss, scale, g0, g1):
    """The same over a sparse pair set (i, j, d); ``mask`` has one bit per pair."""
    has_mask = mask.shape[0] > 0
    has_alpha = alpha.shape[0] > 0
    want = g0.shape[0] > 0
    total = 0.0
    for p in range(d.shape[0]):
        if has_mask and not mask[p]:
            continue
        a, c = i[p], j[p]
        dx = y0[a] - y0[c]
        dy = y1[a] - y1[c]
        e = np.sqrt(dx * dx + dy * dy)
        rho, phi, den = _rho_phi(d[p] - e, loss, scale)
        w = alpha[a] * alpha[c] if has_alpha else 1.0
        total += w * rho
        if want:
            b = w * phi / (den * max(e, _E_FLOOR))
            g0[a] -= b * dx
            g1[a] -= b * dy
            g0[c] += b * dx
            g1[c] += b * dy
    return total


@njit(cache=True, nogil=True, inline="always")
def _guttman_row(Di, x0, x1, x2, xi, yi, zi, o0, o1, o2):
    """Row i's pairs (i, j > i) as slices [i + 1:] (so that they vectorise, as
    the stress kernel's): their stress terms, d_ij^2 and B(X) X terms, row j's
    added into (o0, o1, o2)."""
    s = 0.0
    sq = 0.0
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    for t in range(Di.shape[0]):
        dx = xi - x0[t]
        dy = yi - x1[t]
        dz = zi - x2[t]
        q = dx * dx + dy * dy + dz * dz
        d = np.sqrt(q)
        r = d - Di[t]
        s += r * r
        sq += q
        ratio = Di[t] / (d if d != 0.0 else 1e-5)
        f0 += ratio * dx
        f1 += ratio * dy
        f2 += ratio * dz
        o0[t] -= ratio * dx
        o1[t] -= ratio * dy
        o2[t] -= ratio * dz
    return s, sq, f0, f1, f2


@njit(cache=True, nogil=True, fastmath=FASTMATH_FLAGS)
def guttman_pass(D, X, out):
    """One pass of metric SMACOF (de Leeuw; Borg & Groenen 1997, ch. 8) at a 3D
    configuration X: its raw stress sum_{i<j} (d_ij - D_ij)^2 and
    sum_{i<j} d_ij^2, and the Guttman transform X+ = B(X) X / n written into
    ``out``, with (B(X) X)_i = sum_j D_ij / d_ij (x_i - x_j) and d_ij = 0 read
    as 1e-5 (scikit-learn's convention). D is read above the diagonal."""
    n = X.shape[0]
    x0, x1, x2 = X[:, 0].copy(), X[:, 1].copy(), X[:, 2].copy()
    o0, o1, o2 = np.zeros(n), np.zeros(n), np.zeros(n)
    stress = 0.0
    squares = 0.0
    for i in range(n - 1):
        j = i + 1
        s, sq, f0, f1, f2 = _guttman_row(D[i, j:], x0[j:], x1[j:], x2[j:], x0[i], x1[i], x2[i],
                                         o0[j:], o1[j:], o2[j:])
        stress += s
        squares += sq
        o0[i] += f0
        o1[i] += f1
        o2[i] += f2
    for i in range(n):
        out[i, 0] = o0[i] / n
        out[i, 1] = o1[i] / n
        out[i, 2] = o2[i] / n
    return stress, squares


def smacof(D: np.ndarray, init: np.ndarray, max_iter: int = 300, eps: float = 1e-6):
    """Metric SMACOF from ``init``, scikit-learn's ``smacof(metric=True, n_init=1)``
    step for step (its Guttman update and its stopping rule, 1.7 and later:
    stop when the stress falls by less than ``eps`` times sum_{i<j} d_ij^2),
    one fused pass per iteration. Returns (X, stress, iterations)."""
    D = np.ascontiguousarray(D, dtype=np.float64)
    X = np.array(init, dtype=np.float64, order="C")
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"smacof embeds in 3D; init is {X.shape}")
    nxt = np.empty_like(X)
    guttman_pass(D, X, nxt)  # the start's stress is never compared (scikit-learn's rule)
    X, nxt = nxt, X
    old = None
    for it in range(1, max_iter + 1):
        stress, squares = guttman_pass(D, X, nxt)  # X is iterate it; nxt becomes it + 1
        if old is not None and (old - stress) / squares < eps:
            return X, stress, it
        if it == max_iter:
            return X, stress, it
        old = stress
        X, nxt = nxt, X
    return X, stress, max_iter


# A PSD matrix with det > this x trace^d is inverted directly, the rest another
# way (the bound of linalg.pinv_psd, which this layer may not import).
_WELL_CONDITIONED = 1e-8


@njit(cache=True, nogil=True, inline="always")
def _symmetric_cofactors(m00, m01, m02, m11, m12, m22):
    """The cofactors of a symmetric 3 x 3 M (its inverse times det: c0 c1 c2 /
    c1 c4 c5 / c2 c5 c8), det, and whether det / trace^3 says M is well
    conditioned (a bound on lambda_min / lambda_max for PSD M)."""
    c0 = m11 * m22 - m12 * m12
    c1 = m12 * m02 - m01 * m22
    c2 = m01 * m12 - m11 * m02
    c4 = m00 * m22 - m02 * m02
    c5 = m01 * m02 - m00 * m12
    c8 = m00 * m11 - m01 * m01
    det = m00 * c0 + m01 * c1 + m02 * c2
    trace = m00 + m11 + m22
    return c0, c1, c2, c4, c5, c8, det, det > _WELL_CONDITIONED * trace * trace * trace and trace > 0.0


@njit(cache=True, nogil=True, inline="always")
def _residual_row(x, P, Y, d, root, t):
    """Anchor t's weighted residual -root (d - e) and its gradient in x."""
    u0 = P[t, 0, 0] * x[0] + P[t, 0, 1] * x[1] + P[t, 0, 2] * x[2] - Y[t, 0]
    u1 = P[t, 1, 0] * x[0] + P[t, 1, 1] * x[1] + P[t, 1, 2] * x[2] - Y[t, 1]
    e = max(np.sqrt(u0 * u0 + u1 * u1), _E_FLOOR)
    s = -root[t] / e
    return (s * (u0 * P[t, 0, 0] + u1 * P[t, 1, 0]), s * (u0 * P[t, 0, 1] + u1 * P[t, 1, 1]),
            s * (u0 * P[t, 0, 2] + u1 * P[t, 1, 2]), -root[t] * (d[t] - e))


@njit(cache=True, nogil=True, fastmath=FASTMATH_FLAGS)
def _gauss_newton_step(x, P, Y, d, root):
    """The least-squares step A s = b of one Gauss-Newton iteration, from the
    3 x 3 normal equations (one vectorised pass over the anchors, no m x 3
    matrix); by LAPACK's gelsd on A itself where they are ill-conditioned
    (cond > ~1e8), as when the anchors' views leave the point's depth open."""
    m00 = m01 = m02 = m11 = m12 = m22 = v0 = v1 = v2 = 0.0
    for t in range(d.shape[0]):
        a0, a1, a2, b = _residual_row(x, P, Y, d, root, t)
        m00 += a0 * a0
        m01 += a0 * a1
        m02 += a0 * a2
        m11 += a1 * a1
        m12 += a1 * a2
        m22 += a2 * a2
        v0 += a0 * b
        v1 += a1 * b
        v2 += a2 * b
    c0, c1, c2, c4, c5, c8, det, good = _symmetric_cofactors(m00, m01, m02, m11, m12, m22)
    if good:
        step = np.empty(3)
        step[0] = (c0 * v0 + c1 * v1 + c2 * v2) / det
        step[1] = (c1 * v0 + c4 * v1 + c5 * v2) / det
        step[2] = (c2 * v0 + c5 * v1 + c8 * v2) / det
        return step
    A = np.empty((d.shape[0], 3))
    b = np.empty(d.shape[0])
    for t in range(d.shape[0]):
        A[t, 0], A[t, 1], A[t, 2], b[t] = _residual_row(x, P, Y, d, root, t)
    # numba's default rcond (machine epsilon) keeps rounding-level singular values
    # as directions to move along, and steps 1e12 along the open depth
    return np.linalg.lstsq(A, b, 1e-10)[0]


@njit(cache=True, nogil=True)
def multilaterate(x, P, Y, d, root, steps):
    """The point whose projected distances to anchors fit ``d``: Gauss-Newton
    from x on sum_t root_t^2 (d_t - ||P_t x - Y_t||)^2, ending when a step is
    below 1e-9 of the point's size. P: (m, 2, 3), Y: (m, 2), d and root: (m,)."""
    x = x.copy()
    for _ in range(steps):
        step = _gauss_newton_step(x, P, Y, d, root)
        x += step
        if np.sqrt(np.sum(step * step)) <= 1e-9 * (1.0 + np.sqrt(np.sum(x * x))):
            break
    return x


@njit(cache=True, nogil=True)
def row_misfits(x, P, Y, d, starts):
    """Per row r (entries starts[r]:starts[r+1]), the median |d_t - ||P_t x - Y_t|||."""
    out = np.empty(starts.shape[0] - 1)
    for r in range(out.shape[0]):
        a, z = starts[r], starts[r + 1]
        res = np.empty(z - a)
        for t in range(a, z):
            u0 = P[t, 0, 0] * x[0] + P[t, 0, 1] * x[1] + P[t, 0, 2] * x[2] - Y[t, 0]
            u1 = P[t, 1, 0] * x[0] + P[t, 1, 1] * x[1] + P[t, 1, 2] * x[2] - Y[t, 1]
            res[t - a] = abs(d[t] - np.sqrt(u0 * u0 + u1 * u1))
        out[r] = median_in_place(res)
    return out


@njit(cache=True, nogil=True)
def pairwise_sum(a):
    """np.sum(a) of a 1-D float64 array, to the bit: numpy's pairwise summation
    (eight accumulators up to 128 entries, halves above, from 0)."""
    n = a.shape[0]
    if n < 8:
        total = 0.0
        for i in range(n):
            total += a[i]
        return total
    if n <= 128:
        r = a[:8].copy()
        i = 8
        while i < n - n % 8:
            for j in range(8):
                r[j] += a[i + j]
            i += 8
        total = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
        for t in range(i, n):
            total += a[t]
        return total
    half = n // 2
    half -= half % 8
    return pairwise_sum(a[:half]) + pairwise_sum(a[half:])


@njit(cache=True, nogil=True)
def place_point(x, P, Y, d, starts, line, sigmas, scouts, reweights, steps):
    """A weak point placed against its rows' anchors (rows r: entries
    starts[r]:starts[r + 1]), as refine's ``_place_weak`` describes: each pair
    of rows multilaterates it from every ceil(n_r / scouts)-th anchor of both,
    the pair whose point has the lowest sum of row misfits truncated at
    ``line`` (over those scouts of every row) wins, and ``reweights`` rounds of
    multilateration follow, each row weighted by its inverse misfit variance
    (floored at ``line / sigmas``), the last over all anchors. One call per
    point: the same arithmetic, in the same order, as the NumPy loop had."""
    n_rows = starts.shape[0] - 1
    few_starts = np.zeros(n_rows + 1, dtype=np.int64)
    picks = np.empty(starts[n_rows], dtype=np.int64)  # enough for every row's scouts
    for r in range(n_rows):
        step = -(-(starts[r + 1] - starts[r]) // scouts)
        count = -(-(starts[r + 1] - starts[r]) // step)
        few_starts[r + 1] = few_starts[r] + count
        for t in range(count):
            picks[few_starts[r] + t] = starts[r] + t * step
    picks = picks[:few_starts[n_rows]]
    fP, fY, fd = P[picks], Y[picks], d[picks]
    best, best_cost = x.copy(), np.inf
    for a in range(n_rows):
        for b in range(a + 1, n_rows):
            pair = np.concatenate((np.arange(few_starts[a], few_starts[a + 1]),
                                   np.arange(few_starts[b], few_starts[b + 1])))
            placed = multilaterate(x, fP[pair], fY[pair], fd[pair], np.ones(pair.shape[0]), steps)
            cost = pairwise_sum(np.minimum(row_misfits(placed, fP, fY, fd, few_starts), line))
            if cost < best_cost:
                best, best_cost = placed, cost
    for last in range(reweights, 0, -1):
        uP, uY, ud, ustarts = (P, Y, d, starts) if last == 1 else (fP, fY, fd, few_starts)
        spread = np.maximum(row_misfits(best, uP, uY, ud, ustarts), line / sigmas)
        root = np.empty(ud.shape[0])
        for r in range(n_rows):
            root[ustarts[r]:ustarts[r + 1]] = np.sqrt(1.0 / (spread[r] * spread[r]))
        best = multilaterate(best, uP, uY, ud, root, steps)
    return best


@njit(cache=True, nogil=True)
def add_view_distances(total, count, ids, D):
    """total[ids, ids] += D and count[ids, ids] += 1 for one view's n x n
    distances, row by row: numpy's fancy-indexed np.ix_ update of the same
    sums took 55 ms for 5 views of 1,024 points (315 ms at 2,048)."""
    for a in range(ids.shape[0]):
        row, seen, Da = total[ids[a]], count[ids[a]], D[a]
        for b in range(ids.shape[0]):
            row[ids[b]] += Da[b]
            seen[ids[b]] += 1


@njit(cache=True, nogil=True)
def row_median_residuals(D, y0, y1, cols):
    """Per row i of a view, the median over j in ``cols`` of |D_ij - e_ij|:
    each observation's misfit, one row at a time (no n x n temporary).
    e_ij as scipy's cdist forms it, so the misfits and the rejections they
    decide are those of the NumPy formulation."""
    out = np.empty(y0.shape[0])
    residuals = np.empty(cols.shape[0])
    c0, c1 = y0[cols], y1[cols]
    for i in range(y0.shape[0]):
        Di = D[i]
        for t in range(cols.shape[0]):
            dx = y0[i] - c0[t]
            dy = y1[i] - c1[t]
            residuals[t] = abs(Di[cols[t]] - np.sqrt(dx * dx + dy * dy))
        out[i] = median_in_place(residuals)
    return out


@njit(cache=True, nogil=True)
def median_in_place(a):
    """np.median(a), overwriting a: the middle element by branch-free
    partitions (:func:`_kth_smallest`), then for an even count the mean of it
    and the smallest element above it, as numpy averages the two middle ones.
    A selection's value does not depend on how it is found: these are the bits
    of :func:`_median_hoare`, which it replaced (2.1x faster on rows of 620
    residuals: Hoare's branches mispredict on every other element) and which
    still takes NaNs, whose order is no order, and arrays of fewer than 3."""
    m = a.shape[0]
    nan = False
    for t in range(m):
        nan |= a[t] != a[t]
    if m < 3 or nan:
        return _median_hoare(a)
    k = (m - 1) // 2
    if m % 2:
        return _kth_smallest(a, np.empty(m), k)
    values = a.copy()
    middle = _kth_smallest(a, np.empty(m), k)
    at_most, above = 0, np.inf
    for t in range(m):
        at_most += values[t] <= middle
        above = min(above, values[t] if values[t] > middle else np.inf)
    return (middle + (middle if at_most >= k + 2 else above)) / 2


@njit(cache=True, nogil=True, inline="always")
def _kth_smallest(a, b, k):
    """The k-th smallest (from 0) of a, a and b its scratch: three-way
    partitions about a median-of-three pivot, written from both ends of the
    other array without branches (an element below the pivot advances the
    front, one above it the back, the pivot's equals fill the gap between),
    then an insertion sort of the last few."""
    lo, hi = 0, a.shape[0]
    src, dst = a, b
    while hi - lo > 24:
        x0, x1, x2 = src[lo], src[(lo + hi) // 2], src[hi - 1]
        pivot = max(min(x0, x1), min(max(x0, x1), x2))
        front, back = lo, hi
        for t in range(lo, hi):
            x = src[t]
            dst[front] = x  # both written: only the side whose cursor moves keeps it
            dst[back - 1] = x
            front += x < pivot
            back -= x > pivot
        if k < front:
            hi = front
        elif k >= back:
            lo = back
        else:
            return pivot
        src, dst = dst, src
    for i in range(lo + 1, hi):
        x = src[i]
        j = i - 1
        while j >= lo and src[j] > x:
            src[j + 1] = src[j]
            j -= 1
        src[j + 1] = x
    return src[k]


@njit(cache=True, nogil=True)
def _median_hoare(a):
    """np.median(a), reordering a: Hoare's selection of the middle element
    (median-of-three pivots), then for an even count the mean of it and the
    smallest element above it, as numpy averages the two middle ones."""
    m = a.shape[0]
    k = (m - 1) // 2
    lo, hi = 0, m - 1
    while lo < hi:
        mid = (lo + hi) // 2  # order a[lo], a[mid], a[hi]: the pivot is their median
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    if m % 2:
        return a[k]
    return (a[k] + np.min(a[k + 1:])) / 2


@njit(cache=True, nogil=True, inline="always")
def _msac_score(distance, m, work, mad, cap):
    """(capped sum, sigma) of the first m distances (of ``work``'s length,
    the rest counted as zeros, as numpy summed a padded row): sigma =
    max(median / mad, 1e-12), the sum of min(distance / sigma, cap) in
    numpy's pairwise order. ``work`` is scratch."""
    work[:m] = distance[:m]
    sigma = max(median_in_place(work[:m]) / mad, 1e-12)
    for i in range(work.shape[0]):
        work[i] = min(distance[i] / sigma, cap) if i < m else 0.0
    return pairwise_sum(work), sigma


@njit(cache=True, nogil=True)
def sampson_costs(F, a, b, mad, cap):
    """The MSAC scores of RANSAC's fundamental matrices F (S, 3, 3) on the
    matches (a, b), homogeneous (n, 3) rows each: per sample s the Sampson
    distances d_i of the matches (Hartley & Zisserman eq. 11.9), its robust
    sigma_s = max(median_i d_i / mad, 1e-12), and sum_i min(d_i / sigma_s, cap)
    summed as numpy sums. Returns the (S,) sums and sigmas; the caller adds
    n log sigma_s (numpy's log, not libm's: the same bits as before).

    One sample at a time, so the (S, n, 3) lines numpy formed for it are never
    made (250 views: 1,270 pairs of ~260 matches, 200 samples each), and the
    GIL is free for the pair threads. The lines are summed term by term where
    numpy's matmul let BLAS fuse them, so a score may differ in its last bits
    from the numpy formulation's (the sample it picks has not, on any pair
    tried: see the dated results page)."""
    samples, n = F.shape[0], a.shape[0]
    totals, sigmas = np.empty(samples), np.empty(samples)
    d, work = np.empty(n), np.empty(n)
    for s in range(samples):
        f = F[s]
        for i in range(n):
            a0, a1, a2, b0, b1, b2 = a[i, 0], a[i, 1], a[i, 2], b[i, 0], b[i, 1], b[i, 2]
            l0 = a0 * f[0, 0] + a1 * f[0, 1] + a2 * f[0, 2]  # F a: the line in b's view
            l1 = a0 * f[1, 0] + a1 * f[1, 1] + a2 * f[1, 2]
            l2 = a0 * f[2, 0] + a1 * f[2, 1] + a2 * f[2, 2]
            m0 = b0 * f[0, 0] + b1 * f[1, 0] + b2 * f[2, 0]  # F^T b: the line in a's
            m1 = b0 * f[0, 1] + b1 * f[1, 1] + b2 * f[2, 1]
            gradient = l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1
            d[i] = abs(b0 * l0 + b1 * l1 + b2 * l2) / np.sqrt(max(gradient, 1e-300))
        totals[s], sigmas[s] = _msac_score(d, n, work, mad, cap)
    return totals, sigmas


@njit(cache=True, nogil=True)
def lowest_cosines(rays, point, n_points, lines):
    """(n_points,) the lowest cosine between any two of each point's unit rays
    (T, 3), rows sorted by ``point``; |cosine| where ``lines`` (a ray and its
    opposite are one line); 1 for a point with fewer than two rays. Each
    cosine summed as numpy's einsum "ti,ti->t" sums three columns here
    ((x0 y0 + x2 y2) + x1 y1: its two-lane loop, checked on 100,000 rows), and
    a NaN kept as np.minimum keeps it: the same bits as the pass over gaps it
    replaces, which made a (T,) mask per gap up to the longest track (116 on
    250 views: 0.22-0.28 s a call, 0.02 s here)."""
    lowest = np.ones(n_points)
    start = 0
    while start < len(point):
        end = start + 1
        while end < len(point) and point[end] == point[start]:
            end += 1
        p = point[start]
        for j in range(start + 1, end):
            for i in range(start, j):
                c = (rays[j, 0] * rays[i, 0] + rays[j, 2] * rays[i, 2]) + rays[j, 1] * rays[i, 1]
                if lines:
                    c = abs(c)
                if np.isnan(c) or c < lowest[p]:
                    if not np.isnan(lowest[p]):
                        lowest[p] = c
        start = end
    return lowest


RANK_DEFICIENT = 1e-10  # min |R_jj| / max |R_jj| of a sample with a null plane


@njit(cache=True, nogil=True, inline="always")
def _null_vector_8x9(At, betas, v):
    """v (9,): a unit vector spanning the null space of the 8 x 9 matrix At^T:
    the last column of Q in At = QR (At, 9 x 8, is overwritten by the
    Householder vectors; ``betas`` (8,) is scratch). Returns min |R_jj| /
    max |R_jj|, which is below 1e-15 for a rank-deficient system (a zero
    column's reflection is the identity: no division by zero)."""
    low, high = np.inf, 0.0
    for j in range(8):
        norm2 = 0.0
        for i in range(j, 9):
            norm2 += At[i, j] * At[i, j]
        betas[j] = 0.0
        low, high = min(low, np.sqrt(norm2)), max(high, np.sqrt(norm2))  # |R_jj|
        if norm2 < 1e-300:  # (no overflow in 2 / length2 below)
            continue
        alpha = -np.sqrt(norm2) if At[j, j] >= 0 else np.sqrt(norm2)  # no cancellation
        At[j, j] -= alpha
        length2 = 0.0
        for i in range(j, 9):
            length2 += At[i, j] * At[i, j]
        betas[j] = 2.0 / length2
        for c in range(j + 1, 8):
            dot = 0.0
            for i in range(j, 9):
                dot += At[i, j] * At[i, c]
            dot *= betas[j]
            for i in range(j, 9):
                At[i, c] -= dot * At[i, j]
    v[:] = 0.0
    v[8] = 1.0
    for j in range(7, -1, -1):  # Q e_9 = H_0 ... H_7 e_9
        dot = 0.0
        for i in range(j, 9):
            dot += At[i, j] * v[i]
        dot *= betas[j]
        for i in range(j, 9):
            v[i] -= dot * At[i, j]
    return low / high if high > 0 else 0.0


@njit(cache=True, nogil=True)
def eight_point_samples(a, b, keys):
    """RANSAC's rank-2 fundamental matrices (S, 3, 3), b^T F a = 0, one per
    row of ``keys`` (S, n): the normalised eight-point method (Hartley &
    Zisserman algorithm 11.1) on the 8 matches (rows of a and b, homogeneous
    (n, 3)) with that row's smallest keys, the first 8 of its argsort for
    distinct keys (so the samples numpy's argpartition drew). Also returns
    the (S,) mask of rank-deficient samples.

    The null vector of each 8 x 9 system by a Householder QR of its
    transpose, not numpy's SVD (which computes all nine right singular
    vectors), then the nearest rank-2 matrix by the SVD of the 3 x 3. Where
    the system has full rank, a matrix differs from the SVD formulation's in
    its last bits (or is its negative, the same epipolar geometry). Where it
    has not (a repeated keypoint: 4 % of the samples on COLMAP's 250-photo
    tracks, min |R_jj| / max |R_jj| below 1e-15, against 8e-6 and above for
    all others), its null space is a plane, QR and SVD pick different vectors
    in it, and the caller recomputes those samples as before."""
    S, n = keys.shape
    out, degenerate = np.empty((S, 3, 3)), np.zeros(S, dtype=np.bool_)
    At, betas, v = np.zeros((9, 8)), np.empty(8), np.empty(9)
    smallest, pick = np.empty(8), np.empty(8, dtype=np.int64)
    F = np.empty((3, 3))
    for s in range(S):
        row, m = keys[s], 0
        for i in range(n):  # insertion into the 8 smallest so far, smallest first
            key = row[i]
            if m == 8 and key >= smallest[7]:
                continue
            p = m if m < 8 else 7
            while p > 0 and smallest[p - 1] > key:
                smallest[p], pick[p] = smallest[p - 1], pick[p - 1]
                p -= 1
            smallest[p], pick[p] = key, i
            m = min(m + 1, 8)
        At[:] = 0.0  # fewer than 8 matches: zero rows, an underdetermined sample
        for r in range(m):
            i = pick[r]
            for u in range(3):
                for w in range(3):
                    At[3 * u + w, r] = b[i, u] * a[i, w]
        degenerate[s] = _null_vector_8x9(At, betas, v) < RANK_DEFICIENT
        for u in range(3):
            for w in range(3):
                F[u, w] = v[3 * u + w]
        U, sv, Vt = np.linalg.svd(F)
        for u in range(3):
            for w in range(3):
                out[s, u, w] = U[u, 0] * sv[0] * Vt[0, w] + U[u, 1] * sv[1] * Vt[1, w]
    return out, degenerate


@njit(cache=True, nogil=True)
def subspace_costs(rows, counts, means, normals, mad, cap):
    """The MSAC scores of RANSAC's affine subspaces on a padded stack of rows
    (B, n, d), the first counts[b] of each real: per sample s of stack b
    (its mean (B, S, d) and orthonormal complement normals (B, S, c, d)) the
    rows' distances to the subspace, their robust sigma = max(median / mad,
    1e-12) and the sum of min(distance / sigma, cap) over the padded row (the
    padding adds zeros, as the numpy formulation summed them). Returns the
    (B, S) sums and sigmas; the caller adds the count times numpy's log.

    One sample at a time: none of the (B, S, n, c) projections numpy formed,
    and the GIL free for the pair threads. A distance may differ from the
    einsum formulation's in its last bits, and with it a score."""
    B, n, d = rows.shape
    S, c = normals.shape[1], normals.shape[2]
    totals, sigmas = np.zeros((B, S)), np.empty((B, S))
    distance, work, offset = np.empty(n), np.empty(n), np.empty(c)
    for b in range(B):
        m = counts[b]
        for s in range(S):
            normal, mean = normals[b, s], means[b, s]
            if m == 0:
                sigmas[b, s] = np.inf
                continue
            for k in range(c):
                offset[k] = 0.0
                for j in range(d):
                    offset[k] += mean[j] * normal[k, j]
            for i in range(m):
                squares = 0.0
                for k in range(c):
                    along = 0.0
                    for j in range(d):
                        along += rows[b, i, j] * normal[k, j]
                    squares += (along - offset[k]) ** 2
                distance[i] = np.sqrt(squares)
            totals[b, s], sigmas[b, s] = _msac_score(distance, m, work, mad, cap)
    return totals, sigmas


_NONE_F = np.empty(0)
_NONE_MASK1 = np.empty(0, dtype=np.bool_)
_NONE_MASK2 = np.empty((0, 0), dtype=np.bool_)


def view_stress(pairs, D, Y, mask, alpha, loss: int, scale: float, want_grad: bool):
    """(stress, dS/dY or None) of one view: dense (``D``) or over ``pairs``."""
    y0, y1 = np.ascontiguousarray(Y[:, 0]), np.ascontiguousarray(Y[:, 1])
    n = len(Y)
    g0 = np.zeros(n) if want_grad else _NONE_F
    g1 = np.zeros(n) if want_grad else _NONE_F
    alpha = _NONE_F if alpha is None else alpha
    if pairs is None:
        total = dense_view(D, y0, y1, _NONE_MASK2 if mask is None else mask, alpha,
                           loss, scale, g0, g1)
    else:
        total = pair_view(pairs[0], pairs[1], pairs[2], y0, y1,
                          _NONE_MASK1 if mask is None else mask, alpha, loss, scale, g0, g1)
    if not want_grad:
        return total, None
    grad = np.column_stack([g0, g1])
    grad *= 2.0  # exact: the same bits as doubling each pair's term
    return total, grad


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's fma): the step BLAS's double kernels chain."""
    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d])),
                            args)
    return types.float64(types.float64, types.float64, types.float64), codegen


@njit(cache=True, nogil=True, inline="always")
def _small_matmul(A, B, C):
    """C = A @ B as numpy's BLAS computes a small product: each entry one
    chain of fused multiply-adds along the inner index, from its first
    product."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            c = A[i, 0] * B[0, j]
            for k in range(1, A.shape[1]):
                c = _fma(A[i, k], B[k, j], c)
            C[i, j] = c


@njit(cache=True, nogil=True)
def grouped_matvecs(M, group, X, point):
    """(T, a): M[group[t]] @ X[point[t]] for a few matrices M (G, a, b), each
    entry the chain of fused multiply-adds numpy's BLAS forms for the
    product X[rows] @ M[g].T of a group's rows (:func:`_small_matmul`), so the
    same bits as :func:`mpe3d.solvers.linalg.matvec_by_group` where BLAS fuses
    and a group has two rows or more (one row goes to BLAS's gemv, which
    rounds otherwise), without its loop of gathers and products over the
    groups (250 views: 2-6 ms a projection, most of it numpy's per-group cost)."""
    out = np.empty((point.shape[0], M.shape[1]))
    for t in range(point.shape[0]):
        m, i = M[group[t]], point[t]
        for a in range(M.shape[1]):
            c = X[i, 0] * m[a, 0]
            for k in range(1, M.shape[2]):
                c = _fma(X[i, k], m[a, k], c)
            out[t, a] = c
    return out


@njit(cache=True, nogil=True)
def pose_jacobians(X, view, point, R, Jr, shift, factor, pinhole, d_x, d_view, d_focal):
    """The Jacobian blocks of the observations (view[t], point[t]) for the
    orthographic, scaled and perspective cameras (:mod:`mpe3d.solvers.sfm.cameras`),
    in one pass and no (T, 3, 3) temporaries: fills du/dx (T, 2, 3), the
    view's rotation and translation columns of d_view (T, 2, per_view; for
    scaled also d/d(log s)), and for the pinhole d_focal (T, 2) = du/d(log f).

    R (K, 3, 3) are the current rotations, Jr (K, 3, 3) SO(3)'s right
    Jacobians at the parameters w, so du/dw = du/dq (-R [x]x J_r); ``shift``
    (K, 3) the pinhole's translations, ``factor`` (K,) its focal lengths or
    the affine cameras' scales. Each product is formed as numpy formed it
    (einsum's order for R x, BLAS's fused chains for the 3 x 3 products), so
    the blocks are numpy's to the bit where numpy's BLAS fuses (x86 OpenBLAS;
    checked in tests/solvers/sfm/test_bundle.py)."""
    H, M, negR, dq = np.zeros((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    dn, focal, du, product = np.zeros((2, 3)), np.empty((2, 2)), np.empty((2, 3)), np.empty((2, 3))
    scaled = not pinhole and d_view.shape[2] > 5
    for t in range(view.shape[0]):
        v, i = view[t], point[t]
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        Rv = R[v]
        q0 = (Rv[0, 0] * x0 + Rv[0, 2] * x2) + Rv[0, 1] * x1  # einsum's order
        q1 = (Rv[1, 0] * x0 + Rv[1, 2] * x2) + Rv[1, 1] * x1
        q2 = (Rv[2, 0] * x0 + Rv[2, 2] * x2) + Rv[2, 1] * x1
        H[0, 1], H[0, 2], H[1, 0], H[1, 2], H[2, 0], H[2, 1] = -x2, x1, x2, -x0, -x1, x0
        for a in range(3):
            for b in range(3):
                negR[a, b] = -Rv[a, b]
        _small_matmul(negR, H, M)
        _small_matmul(M, Jr[v], dq)  # dq/dw
        s = factor[v]
        if not pinhole:
            for a in range(2):
                for b in range(3):
                    d_x[t, a, b] = s * Rv[a, b]
                    d_view[t, a, b] = s * dq[a, b]
            d_view[t, 0, 3] = d_view[t, 1, 4] = 1.0
            if scaled:
                d_view[t, 0, 5], d_view[t, 1, 5] = s * q0, s * q1
            continue
        p0, p1, p2 = q0 + shift[v, 0], q1 + shift[v, 1], q2 + shift[v, 2]
        n0, n1 = p0 / p2, p1 / p2
        dn[0, 0] = dn[1, 1] = 1 / p2
        dn[0, 2], dn[1, 2] = -n0 / p2, -n1 / p2
        focal[0, 0], focal[0, 1], focal[1, 0], focal[1, 1] = s * 1.0, s * 0.0, s * 0.0, s * 1.0
        _small_matmul(focal, dn, du)  # du/dp; f I as a matrix, as numpy had it: its signed zeros
        _small_matmul(du, Rv, product)
        d_x[t] = product
        _small_matmul(du, dq, product)
        for a in range(2):
            for b in range(3):
                d_view[t, a, b] = product[a, b]
                d_view[t, a, 3 + b] = du[a, b]
        d_focal[t, 0], d_focal[t, 1] = s * n0, s * n1


# OpenBLAS's double GEMM splits a long inner dimension into blocks of at most this
# many terms (GEMM_Q), a split rounded to its unroll of 4, and adds each block's
# sum into the result: :func:`l2_views` sums G^T X the same way.
_GEMM_Q, _GEMM_UNROLL = 256, 4


@njit(cache=True, nogil=True)
def _gemm_block(k):
    """The length of OpenBLAS's next inner block when ``k`` terms are left."""
    if k >= 2 * _GEMM_Q:
        return _GEMM_Q
    if k > _GEMM_Q:
        return (k // 2 + _GEMM_UNROLL - 1) // _GEMM_UNROLL * _GEMM_UNROLL
    return k


@njit(cache=True, nogil=True)
def _project(X, ids, Pk, y0, y1):
    """y = P^k x_i for the view's points, as numpy's X[ids] @ P^k.T computes
    it through BLAS: a chain of fused multiply-adds over the 3 coordinates."""
    for t in range(ids.shape[0]):
        i = ids[t]
        y0[t] = _fma(X[i, 2], Pk[0, 2], _fma(X[i, 1], Pk[0, 1], X[i, 0] * Pk[0, 0]))
        y1[t] = _fma(X[i, 2], Pk[1, 2], _fma(X[i, 1], Pk[1, 1], X[i, 0] * Pk[1, 0]))


@njit(cache=True, nogil=True)
def _pull_back(X, ids, Pk, gy0, gy1, gX, gPk, want_P):
    """gX[ids] += G P^k and gPk = G^T X[ids], G = [gy0 gy1], in numpy's (BLAS's) order."""
    for t in range(ids.shape[0]):
        i = ids[t]
        for c in range(3):
            gX[i, c] += _fma(gy1[t], Pk[1, c], gy0[t] * Pk[0, c])
    if not want_P:
        return
    gPk[:, :] = 0.0
    start = 0
    while start < ids.shape[0]:
        stop = start + _gemm_block(ids.shape[0] - start)
        for c in range(3):
            a0 = 0.0
            a1 = 0.0
            for t in range(start, stop):
                x = X[ids[t], c]
                a0 = _fma(gy0[t], x, a0)
                a1 = _fma(gy1[t], x, a1)
            gPk[0, c] += a0
            gPk[1, c] += a1
        start = stop


@njit(cache=True, nogil=True)
def l2_views(X, P, D, D_start, ids, ids_start, keep, keep_start, compact, alpha, alpha_start,
             want_grad, want_P, gX, gP):
    """Eq. 1 (loss l2, every pair) summed over all dense views in one call,
    with dS/dX added into ``gX`` and dS/dP^k written into ``gP`` (``want_P``).

    The same arithmetic, term for term, as :meth:`Stress.value_and_grad`'s
    loop over views (image points by BLAS, :func:`view_stress`, the pull-back
    by BLAS), without its Python around each view, which was most of the time
    on many small views (250 photos' tracks). View k holds the points
    ``ids[ids_start[k]:ids_start[k + 1]]``, of which the rows ``keep[...]``
    when ``compact[k]``, their distances flattened from ``D_start[k]`` and
    their weights ``alpha[alpha_start[k]:...]`` (empty: all 1)."""
    total = 0.0
    no_mask = np.zeros((0, 0), dtype=np.bool_)
    for k in range(P.shape[0]):
        view = ids[ids_start[k]:ids_start[k + 1]]
        n = view.shape[0]
        y0, y1 = np.empty(n), np.empty(n)
        _project(X, view, P[k], y0, y1)
        rows = keep[keep_start[k]:keep_start[k + 1]]
        if compact[k]:  # loops, not fancy indexing: a third of the compile time
            u0, u1 = np.empty(rows.shape[0]), np.empty(rows.shape[0])
            for t in range(rows.shape[0]):
                u0[t], u1[t] = y0[rows[t]], y1[rows[t]]
            y0, y1 = u0, u1
        m = y0.shape[0]
        g0 = np.zeros(m if want_grad else 0)
        g1 = np.zeros(m if want_grad else 0)
        total += _dense_l2(D[D_start[k]:D_start[k] + m * m].reshape(m, m), y0, y1, no_mask,
                           alpha[alpha_start[k]:alpha_start[k + 1]], 1.0, g0, g1)
        if not want_grad:
            continue
        g0 *= 2.0  # as view_stress: exact
        g1 *= 2.0
        if compact[k]:
            gy0, gy1 = np.zeros(n), np.zeros(n)
            for t in range(rows.shape[0]):
                gy0[rows[t]], gy1[rows[t]] = g0[t], g1[t]
            g0, g1 = gy0, gy1
        _pull_back(X, view, P[k], g0, g1, gX, gP[k], want_P)
    return total


# Eigenvalues below this share of the largest are dropped, as numpy's pinv's rcond.
_RCOND = 1e-15


@njit(cache=True, nogil=True)
def _pinv_sym(M, out):
    """out = pinv(M) for a small symmetric PSD M, by cyclic Jacobi rotations:
    plain loops, where numba's LAPACK wrappers (det, inv, pinv) added 5 s to
    the kernels' first compile."""
    n = M.shape[0]
    A = M.copy()
    V = np.eye(n)
    for _ in range(50):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += A[p, q] * A[p, q]
        if off <= 1e-30 * (np.sum(A * A) + 1e-300):
            break
        for p in range(n):
            for q in range(p + 1, n):
                if A[p, q] == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * A[p, q])
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * c
                for r in range(n):  # A <- J^T A J, V <- V J
                    arp, arq = A[r, p], A[r, q]
                    A[r, p], A[r, q] = c * arp - sn * arq, sn * arp + c * arq
                for r in range(n):
                    apr, aqr = A[p, r], A[q, r]
                    A[p, r], A[q, r] = c * apr - sn * aqr, sn * apr + c * aqr
                for r in range(n):
                    vrp, vrq = V[r, p], V[r, q]
                    V[r, p], V[r, q] = c * vrp - sn * vrq, sn * vrp + c * vrq
    top = 0.0
    for p in range(n):
        top = max(top, abs(A[p, p]))
    out[:] = 0.0
    for k in range(n):
        if A[k, k] > _RCOND * top:
            for p in range(n):
                for q in range(n):
                    out[p, q] += V[p, k] * V[q, k] / A[k, k]


@njit(cache=True, nogil=True)
def _pinv_psd3(M, out):
    """out = pinv(M) for a symmetric PSD 3 x 3 M: the cofactor inverse where
    it is well conditioned, :func:`_pinv_sym` otherwise."""
    c0, c1, c2, c4, c5, c8, det, good = _symmetric_cofactors(M[0, 0], M[0, 1], M[0, 2], M[1, 1],
                                                             M[1, 2], M[2, 2])
    if not good:
        _pinv_sym(M, out)
        return
    out[0, 0], out[0, 1], out[0, 2] = c0 / det, c1 / det, c2 / det
    out[1, 0], out[1, 1], out[1, 2] = c1 / det, c4 / det, c5 / det
    out[2, 0], out[2, 1], out[2, 2] = c2 / det, c5 / det, c8 / det


@njit(cache=True, nogil=True)
def _fit_affine_views(X, view, point, z, informative, AtA, Atz, L, t):
    """Each view's [L_k; t_k^T] from [x_i, 1] -> z_t over the informative
    observations: one 4 x 4 least-squares system per view (zero if none)."""
    AtA[:] = 0.0
    Atz[:] = 0.0
    a = np.ones(4)
    for s in range(view.shape[0]):
        if not informative[s]:
            continue
        k, i = view[s], point[s]
        a[0], a[1], a[2] = X[i, 0], X[i, 1], X[i, 2]
        for p in range(4):
            for q in range(4):
                AtA[k, p, q] += a[p] * a[q]
            Atz[k, p, 0] += a[p] * z[s, 0]
            Atz[k, p, 1] += a[p] * z[s, 1]
    inverse = np.empty((4, 4))
    for k in range(AtA.shape[0]):
        _pinv_sym(AtA[k], inverse)
        for c in range(2):
            for p in range(4):
                value = inverse[p, 0] * Atz[k, 0, c] + inverse[p, 1] * Atz[k, 1, c] \
                    + inverse[p, 2] * Atz[k, 2, c] + inverse[p, 3] * Atz[k, 3, c]
                if p < 3:
                    L[k, p, c] = value
                else:
                    t[k, c] = value


@njit(cache=True, nogil=True)
def _fit_affine_points(L, t, view, point, z, X, lhs, rhs):
    """Each point from (sum L_k L_k^T) x_i = sum L_k (z_t - t_k) over its
    observations: a 3 x 3 system per point (zero if it has none)."""
    lhs[:] = 0.0
    rhs[:] = 0.0
    for s in range(view.shape[0]):
        k, i = view[s], point[s]
        r0, r1 = z[s, 0] - t[k, 0], z[s, 1] - t[k, 1]
        for p in range(3):
            rhs[i, p] += L[k, p, 0] * r0 + L[k, p, 1] * r1
            for q in range(3):
                lhs[i, p, q] += L[k, p, 0] * L[k, q, 0] + L[k, p, 1] * L[k, q, 1]
    inverse = np.empty((3, 3))
    for i in range(X.shape[0]):
        _pinv_psd3(lhs[i], inverse)
        for p in range(3):
            X[i, p] = inverse[p, 0] * rhs[i, 0] + inverse[p, 1] * rhs[i, 1] + inverse[p, 2] * rhs[i, 2]


@njit(cache=True, nogil=True)
def affine_als(view, point, z, X, informative, n_views, max_iter, tol, floor):
    """Alternating least squares for z_t ~ L_k^T x_i + t_k (observation t of
    point i in view k) from the points X: views fitted to the informative
    observations, then every point to its views, until the RMS residual
    improves by at most ``tol`` of itself or falls to ``floor``. Returns the
    points, the L_k (K, 3, 2), the RMS and the sweeps made."""
    X = X.copy()
    T = view.shape[0]
    AtA, Atz = np.empty((n_views, 4, 4)), np.empty((n_views, 4, 2))
    L, t = np.zeros((n_views, 3, 2)), np.zeros((n_views, 2))
    lhs, rhs = np.empty((X.shape[0], 3, 3)), np.empty((X.shape[0], 3))
    previous, rms, sweep = np.finfo(np.float64).max, 0.0, 0
    for sweep in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        _fit_affine_views(X, view, point, z, informative, AtA, Atz, L, t)
        _fit_affine_points(L, t, view, point, z, X, lhs, rhs)
        squares = 0.0
        for s in range(T):
            k, i = view[s], point[s]
            for c in range(2):
                u = L[k, 0, c] * X[i, 0] + L[k, 1, c] * X[i, 1] + L[k, 2, c] * X[i, 2] + t[k, c] - z[s, c]
                squares += u * u
        rms = np.sqrt(squares / (2 * T))
        if previous - rms <= tol * previous or rms <= floor:
            break
        previous = rms
    return X, L, rms, sweep


warmed = False
_WARM_Y = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # three image points: the warm-up's view
_warm_losses: set = set()  # the robust losses' dense kernels warmed in this process


@njit(cache=True, nogil=True, inline="always")
def _add_both_orders(block, ya, yb):
    """block += ya^T yb + yb^T ya, summed so that it stays symmetric to the bit."""
    for p in range(block.shape[0]):
        for q in range(block.shape[1]):
            block[p, q] += (ya[0, p] * yb[0, q] + ya[1, p] * yb[1, q] + ya[2, p] * yb[2, q]) \
                + (ya[0, q] * yb[0, p] + ya[1, q] * yb[1, p] + ya[2, q] * yb[2, p])


@njit(cache=True, nogil=True)
def schur_order(Y, view, starts, n_views, per_view):
    """The view-independent part of :func:`schur_rows`: each observation's
    point, each point's sum of its observations' shared columns (``totals``),
    the shared block D of S, each view's observations in point order (a
    stable counting sort: ``order``, view k's at ``first[k]:first[k + 1]``),
    and each view's share of the pairs (``work``, to split the views among
    threads)."""
    n_points, T = len(starts) - 1, len(view)
    ns = Y.shape[2] - per_view
    D = np.zeros((ns, ns))
    totals = np.zeros((n_points, 3, ns))
    point = np.empty(T, dtype=np.int64)  # each observation's
    work = np.zeros(n_views)
    for i in range(n_points):
        total = totals[i]
        for a in range(starts[i], starts[i + 1]):
            point[a] = i
            work[view[a]] += starts[i + 1] - a
            for j in range(3):
                for s in range(ns):
                    total[j, s] += Y[a, j, per_view + s]
        for s in range(ns):
            for u in range(ns):
                D[s, u] += total[0, s] * total[0, u] + total[1, s] * total[1, u] \
                    + total[2, s] * total[2, u]
    first = np.zeros(n_views + 1, dtype=np.int64)
    for a in range(T):
        first[view[a] + 1] += 1
    for k in range(n_views):
        first[k + 1] += first[k]
    order, fill = np.empty(T, dtype=np.int64), first[:-1].copy()
    for a in range(T):
        order[fill[view[a]]] = a
        fill[view[a]] += 1
    return point, totals, D, order, first, work


@njit(cache=True, nogil=True)
def schur_rows(Y, Z, view, starts, point, totals, order, first, B, C, k0, k1):
    """Rows k0:k1 of the blocks of S = sum over points i of Y_i^T Y_i: Y (T, 3,
    c) holds each observation's U_i^-1/2 W_t, grouped by point (point i's
    observations are rows starts[i]:starts[i + 1]); its first ``per_view``
    columns belong to the observation's ``view``, the rest are shared by all
    views (a lens); Z is Y's per-view columns, contiguous. ``point``,
    ``totals``, ``order`` and ``first`` are :func:`schur_order`'s.

    Fills B[k] (B: (K, K, per_view, per_view), a workspace kept between
    calls, whose pages stay mapped: a fresh 18 MB array at 250 views cost more
    page faults than the sums) with B[k, l] the block of views k and l, and
    C[k] with the block of view k and the shared columns. A point's pair of
    views is summed once, into B[k, l] for its observations in the order
    given (the caller adds the transposes; an observation's own block B[k, k]
    is whole); the shared columns of a point's observations were summed first
    (``totals``), so the view-lens blocks cost m_i, not m_i^2.

    The pairs are visited view by view (each view's observations in point
    order, each with the later observations of its point), so that the blocks
    written, B[k, :], are one view's row: 72 KB at 250 views, which stays in
    cache, where a pass point by point wrote all over B's 18 MB (1.1-1.3x on
    250 views). Every block still sums its points in increasing order, and
    only row k's pass writes B[k] and C[k]: however the rows are split among
    threads, S is the same to the bit."""
    per_view = B.shape[2]
    ns = Y.shape[2] - per_view
    for k in range(k0, k1):
        row = B[k]
        row[:] = 0.0
        C[k] = 0.0
        for o in range(first[k], first[k + 1]):
            a = order[o]
            total = totals[point[a]]
            for p in range(per_view):
                y0, y1, y2 = Y[a, 0, p], Y[a, 1, p], Y[a, 2, p]
                for s in range(ns):
                    C[k, p, s] += y0 * total[0, s] + y1 * total[1, s] + y2 * total[2, s]
            end = starts[point[a] + 1]
            if per_view == 6:  # a loop of its own: the test inside it cost the unrolling
                for b in range(a, end):
                    vb = view[b]
                    block = row[vb]
                    if b != a and vb == k:
                        _add_both_orders(block, Y[a], Y[b])
                        continue
                    zb = Z[b]
                    for p in range(6):
                        y0, y1, y2 = Z[a, 0, p], Z[a, 1, p], Z[a, 2, p]
                        for q in range(6):
                            block[p, q] += y0 * zb[0, q] + y1 * zb[1, q] + y2 * zb[2, q]
                continue
            for b in range(a, end):
                block = row[view[b]]
                if b != a and view[b] == k:  # the point seen twice in a view: the
                    _add_both_orders(block, Y[a], Y[b])  # transpose lands here too
                    continue
                zb = Z[b]
                for p in range(per_view):
                    y0, y1, y2 = Z[a, 0, p], Z[a, 1, p], Z[a, 2, p]
                    for q in range(per_view):
                        block[p, q] += y0 * zb[0, q] + y1 * zb[1, q] + y2 * zb[2, q]


@njit(cache=True, nogil=True)
def transposed_products(A, B):
    """(T, a, b): A[t]^T @ B[t] for A (T, r, a) and B (T, r, b), each as numpy's
    BLAS forms it (:func:`_small_matmul`: the same bits where it fuses),
    without numpy's one BLAS call per t: the Gauss-Newton blocks J_x^T w J_x
    and J_x^T w J_c of every observation."""
    out = np.empty((A.shape[0], A.shape[2], B.shape[2]))
    for t in range(A.shape[0]):
        _small_matmul(A[t].T, B[t], out[t])
    return out


@njit(cache=True, nogil=True)
def whitened_blocks(root, W, point, rows):
    """Y (T, 3, c) with Y[t] = root[point[t]] @ W[rows[t]]: each observation's
    U_i^-1/2 W_t for :func:`reduced_system`, in the order ``rows`` (by point),
    each product as numpy's BLAS forms it (:func:`_small_matmul`), without its
    one BLAS call per observation (250 views x 3,000 points: 48 -> 25 ms, the
    rest gathering W by point)."""
    Y = np.empty((len(rows), 3, W.shape[2]))
    for t in range(len(rows)):
        _small_matmul(root[point[t]], W[rows[t]], Y[t])
    return Y


_THREADED_PAIRS = 100_000  # about 5 ms of schur_rows: threads for more


def reduced_system(V, Y, view, starts, blocks: np.ndarray, threads: int = 1) -> np.ndarray:
    """The upper triangle of the reduced camera system S = V - sum_i Y_i^T Y_i,
    columns per_view * k + p for view k's parameter p, then the shared ones,
    from :func:`schur_rows`' blocks (``blocks``: its (K, K, per_view,
    per_view) workspace), on up to ``threads`` threads, each a range of views
    of about equal work (the same bits for any count); S's lower triangle is
    V's (Cholesky reads the upper one)."""
    K, pv = blocks.shape[0], blocks.shape[2]
    size = K * pv + Y.shape[2] - pv
    if V.shape != (size, size) or blocks.shape != (K, K, pv, pv):  # the kernels index unchecked
        raise ValueError(f"reduced_system: V {V.shape} and blocks {blocks.shape} do not fit "
                         f"{K} views of {pv} parameters and {Y.shape[2] - pv} shared")
    point, totals, D, order, first, work = schur_order(Y, view, starts, K, pv)
    C = np.empty((K, pv, Y.shape[2] - pv))
    # below _THREADED_PAIRS pairs the threads' start costs more than they share
    bounds = even_split(work, threads if work.sum() >= _THREADED_PAIRS else 1)
    ranges = list(zip(bounds[:-1], bounds[1:]))
    Z = np.ascontiguousarray(Y[:, :, :pv])
    rows = functools.partial(schur_rows, Y, Z, view, starts, point, totals, order, first, blocks, C)
    map_in_order(lambda views: rows(*views), ranges, len(ranges))  # the kernel releases the GIL
    return _subtract_blocks(V.copy(), blocks, C, D)


@njit(cache=True, nogil=True)
def _subtract_blocks(S, B, C, D):
    """S's upper triangle less the symmetric matrix of :func:`schur_rows`'
    blocks, in one pass along S's rows: each pair of views was summed on one
    side (B[k, l] or B[l, k]), so its block is their sum; a view's own block is
    whole. Only the upper triangle: the dense matrix's column writes cost as
    much as its row writes at 250 views."""
    K, pv, ns = B.shape[0], B.shape[2], D.shape[0]
    base = K * pv
    for k in range(K):
        for p in range(pv):
            row = S[k * pv + p]
            for q in range(p, pv):
                row[k * pv + q] -= B[k, k, p, q]
            for l in range(k + 1, K):
                for q in range(pv):
                    row[l * pv + q] -= B[k, l, p, q] + B[l, k, q, p]
            for s in range(ns):
                row[base + s] -= C[k, p, s]
    for s in range(ns):
        for u in range(s, ns):
            S[base + s, base + u] -= D[s, u]
    return S


def warm(loss: str = "l2", *, part: int = 0, parts: int = 1) -> None:
    """Compile (or load from the on-disk cache) every kernel a solve with the
    stress loss ``loss`` can call now, once per process, so that no solve pays
    for it inside its timed region.

    A robust loss's dense kernel (about 6 s of a 37 s first compile each) is
    compiled only when a solve asks for that loss: most installs never do.

    With ``parts`` > 1, only the share ``part`` (0 <= part < parts) of every
    kernel, each robust loss's included, whatever ``loss``. Numba compiles one
    kernel at a time in a process, so ``parts`` processes compile a fresh
    install's kernels side by side (the test suite does, before its workers
    start; they then load them from the cache)."""
    if parts > 1:
        if not 0 <= part < parts:
            raise ValueError(f"part must be in [0, {parts}), got {part}")
        for step in _share(_warm_steps(every_loss=True), part, parts):
            step()
        return
    _warm_loss(LOSS_CODES.get(loss, L2))
    global warmed
    if warmed:
        return
    for _, step in _warm_steps(every_loss=False):
        step()
    warmed = True


def _share(steps: list, part: int, parts: int) -> list:
    """The steps of ``part`` when ``steps`` (cost, call), longest first, go
    one by one to the part with the least cost so far."""
    loads, mine = [0.0] * parts, []
    for cost, call in steps:
        least = loads.index(min(loads))
        loads[least] += cost
        if least == part:
            mine.append(call)
    return mine


def _warm_steps(every_loss: bool) -> list:
    """One call a kernel, each compiling it all (one signature a kernel), with
    its compile's seconds on a fresh cache (2026-12-05, one process after
    another; only their ratios matter), longest first."""
    Y = _WARM_Y
    ints = functools.partial(np.array, dtype=np.int64)
    P, d = np.zeros((3, 2, 3)), np.ones(3)
    P[:, 0, 0] = P[:, 1, 1] = 1.0
    losses = [(6.3, functools.partial(_warm_loss, code)) for code in (HUBER, SOFT_L1)] if every_loss else []
    return [
        (10.9, lambda: place_point(np.zeros(3), P, Y, d, np.array([0, 1, 3]), 1.0, 5.0, 64, 1, 1)),
        *losses,
        (6.1, lambda: view_stress(None, np.ones((3, 3)), Y, None, None, L2, 1.0, True)),
        (5.3, lambda: pose_jacobians(np.ones((1, 3)), ints([0]), ints([0]), np.ones((1, 3, 3)),
                                     np.ones((1, 3, 3)), np.ones((1, 3)), np.ones(1), True,
                                     np.empty((1, 2, 3)), np.zeros((1, 2, 6)), np.empty((1, 2)))),
        (4.8, lambda: affine_als(np.array([0, 1]), np.array([0, 0]), np.ones((2, 2)), np.zeros((1, 3)),
                                 np.ones(2, dtype=np.bool_), 2, 1, 0.0, 0.0)),
        # two views of one parameter and one shared: V is (2 * 1 + 1) square
        (3.0, lambda: reduced_system(np.eye(3), np.ones((2, 3, 2)), np.array([0, 1]), np.array([0, 2]),
                                     np.empty((2, 2, 1, 1)))),
        (2.4, lambda: eight_point_samples(np.ones((9, 3)), np.ones((9, 3)), np.ones((1, 9)))),
        (2.0, lambda: l2_views(np.eye(3), np.eye(3)[None, :2], np.ones(9), ints([0, 9]), ints([0, 1, 2]),
                               ints([0, 3]), ints([]), ints([0, 0]), np.zeros(1, dtype=np.bool_),
                               np.empty(0), ints([0, 0]), True, True, np.zeros((3, 3)),
                               np.zeros((1, 2, 3)))),
        (1.0, lambda: sampson_costs(np.ones((1, 3, 3)), np.ones((2, 3)), np.ones((2, 3)), 1.0, 1.0)),
        (1.0, lambda: guttman_pass(np.ones((3, 3)), np.eye(3), np.empty((3, 3)))),
        (0.9, lambda: subspace_costs(np.ones((1, 2, 4)), np.array([2]), np.ones((1, 1, 4)),
                                     np.ones((1, 1, 1, 4)), 1.0, 1.0)),
        (0.5, lambda: lowest_cosines(np.eye(3), ints([0, 0, 1]), 2, False)),
        (0.4, lambda: view_stress((np.array([0, 1]), np.array([1, 2]), np.ones(2)), None, Y, None, None,
                                  L2, 1.0, True)),
        (0.3, lambda: grouped_matvecs(np.ones((1, 2, 3)), ints([0]), np.ones((1, 3)), ints([0]))),
        (0.3, lambda: transposed_products(np.ones((1, 2, 3)), np.ones((1, 2, 3)))),
        (0.3, lambda: add_view_distances(np.zeros((2, 2)), np.zeros((2, 2), dtype=np.int32), ints([0, 1]),
                                         np.ones((2, 2)))),
        (0.3, lambda: row_median_residuals(np.ones((3, 3)), Y[:, 0].copy(), Y[:, 1].copy(), np.arange(3))),
        (0.3, lambda: whitened_blocks(np.ones((1, 3, 3)), np.ones((1, 3, 6)), ints([0]), ints([0]))),
    ]


def _warm_loss(code: int) -> None:
    """The dense stress kernel of a robust loss, once per process."""
    if code != L2 and code not in _warm_losses:
        view_stress(None, np.ones((3, 3)), _WARM_Y, None, None, code, 1.0, True)
        _warm_losses.add(code)
