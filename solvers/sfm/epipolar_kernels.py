"""The two-view tests' compiled passes: RANSAC's eight-point samples (the
null vector by a Householder QR, rank 2 by a 3 x 3 SVD) and the MSAC scores
of fundamental-matrix and affine-subspace samples (Sampson and subspace
distances, their robust sigma by the median numpy takes, the capped sum in
numpy's pairwise order). nogil, one sample at a time, so that the view pairs'
threads overlap.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mpe3d.solvers.point_kernels import median_in_place, pairwise_sum
from mpe3d.solvers.warmup import warm_up


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


@warm_up(1.0, lambda k: k(np.ones((1, 3, 3)), np.ones((2, 3)), np.ones((2, 3)), 1.0, 1.0))
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


@warm_up(2.4, lambda k: k(np.ones((9, 3)), np.ones((9, 3)), np.ones((1, 9))))
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


@warm_up(0.9, lambda k: k(np.ones((1, 2, 4)), np.array([2]), np.ones((1, 1, 4)), np.ones((1, 1, 1, 4)),
                           1.0, 1.0))
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
