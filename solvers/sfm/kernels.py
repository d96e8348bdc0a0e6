"""Bundle adjustment's compiled passes: the camera Jacobians of the
orthographic, scaled and perspective cameras, J^T w J and U^-1/2 W per
observation, the Schur term of the reduced camera system (split by views
among threads, each view's rows in a fixed order), and the widest ray angles
that triangulation checks. Each small product is formed as numpy's BLAS forms
it (:func:`mpe3d.solvers.kernels.small_matmul`), so the results are the bits
numpy gave where a probe finds the BLAS fuses."""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from mpe3d.solvers.kernels import fma, small_matmul
from mpe3d.solvers.threads import even_split, map_in_order
from mpe3d.solvers.warmup import warm_up

_ints = functools.partial(np.array, dtype=np.int64)  # the warm-ups' index arrays


@warm_up(0.5, lambda k: k(np.eye(3), _ints([0, 0, 1]), 2, False))
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


@warm_up(0.3, lambda k: k(np.ones((1, 2, 3)), _ints([0]), np.ones((1, 3)), _ints([0])))
@njit(cache=True, nogil=True)
def grouped_matvecs(M, group, X, point):
    """(T, a): M[group[t]] @ X[point[t]] for a few matrices M (G, a, b), each
    entry the chain of fused multiply-adds numpy's BLAS forms for the
    product X[rows] @ M[g].T of a group's rows (:func:`small_matmul`), so the
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
                c = fma(X[i, k], m[a, k], c)
            out[t, a] = c
    return out


@warm_up(5.3, lambda k: k(np.ones((1, 3)), _ints([0]), _ints([0]), np.ones((1, 3, 3)), np.ones((1, 3, 3)),
                           np.ones((1, 3)), np.ones(1), True, np.empty((1, 2, 3)), np.zeros((1, 2, 6)),
                           np.empty((1, 2))))
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
        small_matmul(negR, H, M)
        small_matmul(M, Jr[v], dq)  # dq/dw
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
        small_matmul(focal, dn, du)  # du/dp; f I as a matrix, as numpy had it: its signed zeros
        small_matmul(du, Rv, product)
        d_x[t] = product
        small_matmul(du, dq, product)
        for a in range(2):
            for b in range(3):
                d_view[t, a, b] = product[a, b]
                d_view[t, a, 3 + b] = du[a, b]
        d_focal[t, 0], d_focal[t, 1] = s * n0, s * n1


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


@warm_up(0.3, lambda k: k(np.ones((1, 2, 3)), np.ones((1, 2, 3))))
@njit(cache=True, nogil=True)
def transposed_products(A, B):
    """(T, a, b): A[t]^T @ B[t] for A (T, r, a) and B (T, r, b), each as numpy's
    BLAS forms it (:func:`small_matmul`: the same bits where it fuses),
    without numpy's one BLAS call per t: the Gauss-Newton blocks J_x^T w J_x
    and J_x^T w J_c of every observation."""
    out = np.empty((A.shape[0], A.shape[2], B.shape[2]))
    for t in range(A.shape[0]):
        small_matmul(A[t].T, B[t], out[t])
    return out


@warm_up(0.3, lambda k: k(np.eye(3)[None].copy()))
@njit(cache=True, nogil=True)
def inverse_roots(U):
    """For each symmetric 3x3 block U_i: M_i = L_i^-1, the inverse of its
    Cholesky factor (U_i = L_i L_i^T, so U_i^-1 = M_i^T M_i and
    W^T U_i^-1 W = (M_i W)^T (M_i W)), and U_i^-1; False when a block is not
    positive definite. A closed form per block: numpy's batched eigh and
    inv of the same blocks took 40% of an iteration at 22,000 points."""
    n = U.shape[0]
    M, inverse = np.zeros((n, 3, 3)), np.empty((n, 3, 3))
    for i in range(n):
        a = U[i]
        p0 = a[0, 0]
        if not p0 > 0.0:
            return M, inverse, False
        l00 = np.sqrt(p0)
        l10, l20 = a[1, 0] / l00, a[2, 0] / l00
        p1 = a[1, 1] - l10 * l10
        if not p1 > 0.0:
            return M, inverse, False
        l11 = np.sqrt(p1)
        l21 = (a[2, 1] - l20 * l10) / l11
        p2 = a[2, 2] - l20 * l20 - l21 * l21
        if not p2 > 0.0:
            return M, inverse, False
        l22 = np.sqrt(p2)
        m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
        m10 = -l10 * m00 * m11
        m21 = -l21 * m11 * m22
        m20 = -(l20 * m00 + l21 * m10) * m22
        m = M[i]
        m[0, 0], m[1, 0], m[1, 1], m[2, 0], m[2, 1], m[2, 2] = m00, m10, m11, m20, m21, m22
        for r in range(3):
            for c in range(r, 3):
                value = 0.0
                for k in range(max(r, c), 3):
                    value += m[k, r] * m[k, c]
                inverse[i, r, c] = value
                inverse[i, c, r] = value
    return M, inverse, True


@warm_up(0.3, lambda k: k(np.ones((1, 3, 3)), np.ones((1, 3, 6)), _ints([0]), _ints([0])))
@njit(cache=True, nogil=True)
def whitened_blocks(root, W, point, rows):
    """Y (T, 3, c) with Y[t] = root[point[t]] @ W[rows[t]]: each observation's
    U_i^-1/2 W_t for :func:`reduced_system`, in the order ``rows`` (by point),
    each product as numpy's BLAS forms it (:func:`small_matmul`), without its
    one BLAS call per observation (250 views x 3,000 points: 48 -> 25 ms, the
    rest gathering W by point)."""
    Y = np.empty((len(rows), 3, W.shape[2]))
    for t in range(len(rows)):
        small_matmul(root[point[t]], W[rows[t]], Y[t])
    return Y


_THREADED_PAIRS = 100_000  # about 5 ms of schur_rows: threads for more


# two views of one parameter and one shared: V is (2 * 1 + 1) square
@warm_up(3.0, lambda k: k(np.eye(3), np.ones((2, 3, 2)), np.array([0, 1]), np.array([0, 2]), np.empty((2, 2, 1, 1))))
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

