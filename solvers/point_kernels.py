"""Compiled passes that place points: SMACOF's Guttman transform, placing one
point against anchors by multilateration (refine's start), the views' summed
distances (the baseline's average), the row medians of residuals, and the
affine factorisation's alternating least squares. The conventions are
:mod:`mpe3d.solvers.kernels`'s: serial loops in a fixed order, optional
inputs as empty arrays, one signature a kernel, cached on disk.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mpe3d.solvers.kernels import E_FLOOR, FASTMATH_FLAGS
from mpe3d.solvers.warmup import warm_up

_WARM_Y = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # three image points: the warm-ups' view
_WARM_P = np.zeros((3, 2, 3))  # three orthographic views
_WARM_P[:, 0, 0] = _WARM_P[:, 1, 1] = 1.0


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
    e = max(np.sqrt(u0 * u0 + u1 * u1), E_FLOOR)
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
def _multilaterate(x, P, Y, d, root, steps):
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


@warm_up(10.9, lambda k: k(np.zeros(3), _WARM_P, _WARM_Y, np.ones(3), np.array([0, 1, 3]), 1.0, 5.0, 64, 1, 1))
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
            placed = _multilaterate(x, fP[pair], fY[pair], fd[pair], np.ones(pair.shape[0]), steps)
            cost = pairwise_sum(np.minimum(row_misfits(placed, fP, fY, fd, few_starts), line))
            if cost < best_cost:
                best, best_cost = placed, cost
    for last in range(reweights, 0, -1):
        uP, uY, ud, ustarts = (P, Y, d, starts) if last == 1 else (fP, fY, fd, few_starts)
        spread = np.maximum(row_misfits(best, uP, uY, ud, ustarts), line / sigmas)
        root = np.empty(ud.shape[0])
        for r in range(n_rows):
            root[ustarts[r]:ustarts[r + 1]] = np.sqrt(1.0 / (spread[r] * spread[r]))
        best = _multilaterate(best, uP, uY, ud, root, steps)
    return best


@warm_up(0.3, lambda k: k(np.zeros((2, 2)), np.zeros((2, 2), dtype=np.int32), np.array([0, 1]),
                           np.ones((2, 2))))
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


@warm_up(0.3, lambda k: k(np.ones((3, 3)), _WARM_Y[:, 0].copy(), _WARM_Y[:, 1].copy(), np.arange(3)))
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


@warm_up(4.8, lambda k: k(np.array([0, 1]), np.array([0, 0]), np.ones((2, 2)), np.zeros((1, 3)),
                           np.ones(2, dtype=np.bool_), 2, 1, 0.0, 0.0))
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

