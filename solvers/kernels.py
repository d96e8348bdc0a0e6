"""The stress kernels: the 3DMPE stress (paper Eq. 1) and its gradient one
view at a time (:func:`view_stress`) or all dense views in one call
(:func:`l2_views`), and SMACOF's Guttman transform. The passes that place
points are :mod:`mpe3d.solvers.point_kernels`'s; the SfM stack's kernels sit
beside it (:mod:`mpe3d.solvers.sfm.kernels`, ``epipolar_kernels``). Each
kernel declares its warm-up where it is defined (:mod:`mpe3d.solvers.warmup`).

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
:func:`mpe3d.solvers.warmup.warm` does so before any solver's clock starts.

Optional inputs are passed as empty arrays rather than ``None``, so that each
kernel has one signature and one compilation.
"""

from __future__ import annotations

import functools

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from mpe3d.options import STRESS_LOSSES
from mpe3d.solvers.warmup import warm_up

_ints = functools.partial(np.array, dtype=np.int64)  # the warm-ups' index arrays
_WARM_Y = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # three image points: the warm-ups' view

# Loss codes: each stress loss's place in mpe3d.options.STRESS_LOSSES, the one list of them.
L2, HUBER, SOFT_L1 = (STRESS_LOSSES.index(name) for name in ("l2", "huber", "soft_l1"))
# Floor on e in 1/e: keeps it finite for coincident images, where r e-terms cancel.
E_FLOOR = 1e-12
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
            b = w * r / max(root * e, E_FLOOR)
        else:
            rho, phi, _ = _rho_phi(r, loss, scale)
            row += w * rho
            b = w * phi / max(e, E_FLOOR)
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
            b = w * phi / (den * max(e, E_FLOOR))
            g0[a] -= b * dx
            g1[a] -= b * dy
            g0[c] += b * dx
            g1[c] += b * dy
    return total


_NONE_F = np.empty(0)
_NONE_MASK1 = np.empty(0, dtype=np.bool_)
_NONE_MASK2 = np.empty((0, 0), dtype=np.bool_)


@warm_up(6.1, lambda k: k(None, np.ones((3, 3)), _WARM_Y, None, None, L2, 1.0, True))
@warm_up(0.4, lambda k: k((np.array([0, 1]), np.array([1, 2]), np.ones(2)), None, _WARM_Y, None, None, L2, 1.0,
                           True), name=f"{__name__}.view_stress.pairs")
@warm_up(6.3, lambda k: k(None, np.ones((3, 3)), _WARM_Y, None, None, HUBER, 1.0, True), loss="huber",
         name=f"{__name__}.view_stress.huber")
@warm_up(6.3, lambda k: k(None, np.ones((3, 3)), _WARM_Y, None, None, SOFT_L1, 1.0, True), loss="soft_l1",
         name=f"{__name__}.view_stress.soft_l1")
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
def fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's fma): the step BLAS's double kernels chain."""
    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d])),
                            args)
    return types.float64(types.float64, types.float64, types.float64), codegen


@njit(cache=True, nogil=True, inline="always")
def small_matmul(A, B, C):
    """C = A @ B as numpy's BLAS computes a small product: each entry one
    chain of fused multiply-adds along the inner index, from its first
    product."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            c = A[i, 0] * B[0, j]
            for k in range(1, A.shape[1]):
                c = fma(A[i, k], B[k, j], c)
            C[i, j] = c


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
        y0[t] = fma(X[i, 2], Pk[0, 2], fma(X[i, 1], Pk[0, 1], X[i, 0] * Pk[0, 0]))
        y1[t] = fma(X[i, 2], Pk[1, 2], fma(X[i, 1], Pk[1, 1], X[i, 0] * Pk[1, 0]))


@njit(cache=True, nogil=True)
def _pull_back(X, ids, Pk, gy0, gy1, gX, gPk, want_P):
    """gX[ids] += G P^k and gPk = G^T X[ids], G = [gy0 gy1], in numpy's (BLAS's) order."""
    for t in range(ids.shape[0]):
        i = ids[t]
        for c in range(3):
            gX[i, c] += fma(gy1[t], Pk[1, c], gy0[t] * Pk[0, c])
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
                a0 = fma(gy0[t], x, a0)
                a1 = fma(gy1[t], x, a1)
            gPk[0, c] += a0
            gPk[1, c] += a1
        start = stop


@warm_up(2.0, lambda k: k(np.eye(3), np.eye(3)[None, :2], np.ones(9), _ints([0, 9]), _ints([0, 1, 2]),
                           _ints([0, 3]), _ints([]), _ints([0, 0]), np.zeros(1, dtype=np.bool_), np.empty(0),
                           _ints([0, 0]), True, True, np.zeros((3, 3)), np.zeros((1, 2, 3))))
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


@warm_up(1.0, lambda k: k(np.ones((3, 3)), np.eye(3), np.empty((3, 3))))
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

