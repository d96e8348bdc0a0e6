"""Compiled passes: the 3DMPE stress (paper Eq. 1) one view at a time, SMACOF's
Guttman transform, and placing one point against anchors.

For each pair i < j of a view the stress kernel forms the image distance
e_ij = ||y_i - y_j||, the residual r_ij = D_ij - e_ij, its weight
w_ij = a_i a_j (the visibility of Eq. 1 taken into [0, 1]) and minibatch bit,
the loss rho(r) and phi(r) = rho'(r) / 2, and adds both rows' gradient terms

    dS/dy_i += -2 w phi(r) (y_i - y_j) / e,   dS/dy_j -= the same,

so that no n x n temporary is ever made: the input distances are read once.
(The kernels sum the terms without the factor 2 and ``view_stress`` doubles
the sums, which is exact.) The loops are serial and in a fixed order, so a
result is the same bits in every process, thread count and backend. Numba
caches the machine code on disk (``cache=True``): a process loads it instead
of compiling again, and :func:`warm` does so before any solver's clock starts.

Optional inputs are passed as empty arrays rather than ``None``, so that each
kernel has one signature and one compilation.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Loss codes, in the order of stress.LOSSES.
L2, HUBER, SOFT_L1 = 0, 1, 2
# Floor on e in 1/e: keeps it finite for coincident images, where r e-terms cancel.
_E_FLOOR = 1e-12


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
def _dense_row(D, y0, y1, mask, alpha, i, loss, scale, g0, g1, has_mask, has_alpha, want):
    """Row i's pairs (i, j > i): their stress, and row i's gradient terms; adds
    row j's terms into (g0, g1). Inlined with constant ``loss`` and flags, so
    that the compiler drops the branches they decide from the inner loop."""
    xi, yi = y0[i], y1[i]
    ai = alpha[i] if has_alpha else 1.0
    row = 0.0
    fi0 = 0.0
    fi1 = 0.0
    for j in range(i + 1, y0.shape[0]):
        dx = xi - y0[j]
        dy = yi - y1[j]
        e = np.sqrt(dx * dx + dy * dy)
        rho, phi, den = _rho_phi(D[i, j] - e, loss, scale)
        w = ai * alpha[j] if has_alpha else 1.0
        if has_mask and not mask[i, j]:
            w = 0.0
        row += w * rho
        if want:
            b = w * phi / (den * max(e, _E_FLOOR))  # half the force: view_stress doubles the sums
            fi0 += b * dx
            fi1 += b * dy
            g0[j] += b * dx
            g1[j] += b * dy
    return row, fi0, fi1


@njit(cache=True, nogil=True, inline="always")
def _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, has_mask, has_alpha, want):
    total = 0.0
    for i in range(y0.shape[0]):
        if loss == L2:
            row, fi0, fi1 = _dense_row(D, y0, y1, mask, alpha, i, L2, scale, g0, g1,
                                       has_mask, has_alpha, want)
        elif loss == HUBER:
            row, fi0, fi1 = _dense_row(D, y0, y1, mask, alpha, i, HUBER, scale, g0, g1,
                                       has_mask, has_alpha, want)
        else:
            row, fi0, fi1 = _dense_row(D, y0, y1, mask, alpha, i, SOFT_L1, scale, g0, g1,
                                       has_mask, has_alpha, want)
        total += row
        if want:
            g0[i] -= fi0
            g1[i] -= fi1
    return total


@njit(cache=True, nogil=True)
def dense_view(D, y0, y1, mask, alpha, loss, scale, g0, g1):
    """Stress of one view over its pairs i < j (D read above the diagonal);
    adds dS/dy into (g0, g1) unless they are empty. ``mask`` (n x n booleans,
    read above the diagonal) and ``alpha`` (n weights) are skipped when empty.
    The plain stress and its gradient, what every iteration of SGD and
    refine asks for, get loops with nothing else in them."""
    has_mask, has_alpha, want = mask.shape[0] > 0, alpha.shape[0] > 0, g0.shape[0] > 0
    if has_mask:
        return _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, True, has_alpha, want)
    if has_alpha:  # refine's rounds without the rejected observations
        if want:
            return _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, True, True)
        return _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, True, False)
    if want:
        return _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, False, True)
    return _dense_rows(D, y0, y1, mask, alpha, loss, scale, g0, g1, False, False, False)


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


@njit(cache=True, nogil=True)
def guttman_pass(D, X, out):
    """One pass of metric SMACOF (de Leeuw; Borg & Groenen 1997, ch. 8) at a 3D
    configuration X: its raw stress sum_{i<j} (d_ij - D_ij)^2 and
    sum_{i<j} d_ij^2, and the Guttman transform X+ = B(X) X / n written into
    ``out``, with (B(X) X)_i = sum_j D_ij / d_ij (x_i - x_j) and d_ij = 0 read
    as 1e-5 (scikit-learn's convention)."""
    n = X.shape[0]
    out[:] = 0.0
    stress = 0.0
    squares = 0.0
    for i in range(n):
        xi, yi, zi = X[i, 0], X[i, 1], X[i, 2]
        o0 = 0.0
        o1 = 0.0
        o2 = 0.0
        for j in range(i + 1, n):
            dx = xi - X[j, 0]
            dy = yi - X[j, 1]
            dz = zi - X[j, 2]
            q = dx * dx + dy * dy + dz * dz
            d = np.sqrt(q)
            r = d - D[i, j]
            stress += r * r
            squares += q
            ratio = D[i, j] / (d if d != 0.0 else 1e-5)
            o0 += ratio * dx
            o1 += ratio * dy
            o2 += ratio * dz
            out[j, 0] -= ratio * dx
            out[j, 1] -= ratio * dy
            out[j, 2] -= ratio * dz
        out[i, 0] += o0
        out[i, 1] += o1
        out[i, 2] += o2
    out /= n
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


@njit(cache=True, nogil=True)
def multilaterate(x, P, Y, d, root, steps):
    """The point whose projected distances to anchors fit ``d``: Gauss-Newton
    from x on sum_t root_t^2 (d_t - ||P_t x - Y_t||)^2, each step a least-squares
    solve (LAPACK's gelsd, as numpy's lstsq), ending when a step is below 1e-9
    of the point's size. P: (m, 2, 3), Y: (m, 2), d and root: (m,)."""
    x = x.copy()
    m = d.shape[0]
    A = np.empty((m, 3))
    b = np.empty(m)
    for _ in range(steps):
        for t in range(m):
            u0 = P[t, 0, 0] * x[0] + P[t, 0, 1] * x[1] + P[t, 0, 2] * x[2] - Y[t, 0]
            u1 = P[t, 1, 0] * x[0] + P[t, 1, 1] * x[1] + P[t, 1, 2] * x[2] - Y[t, 1]
            e = max(np.sqrt(u0 * u0 + u1 * u1), _E_FLOOR)
            for c in range(3):  # d r / d x, weighted
                A[t, c] = -root[t] * (u0 * P[t, 0, c] + u1 * P[t, 1, c]) / e
            b[t] = -root[t] * (d[t] - e)
        step = np.linalg.lstsq(A, b)[0]
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
        out[r] = np.median(res)
    return out


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


_warm = False


def warm() -> None:
    """Compile (or load from the on-disk cache) every kernel now, once per
    process, so that no solve pays for it inside its timed region."""
    global _warm
    if _warm:
        return
    Y = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # One signature per kernel (the loss is an argument), so one call each compiles it all.
    view_stress(None, np.ones((3, 3)), Y, None, None, L2, 1.0, True)
    view_stress((np.array([0, 1]), np.array([1, 2]), np.ones(2)), None, Y, None, None, L2, 1.0, True)
    guttman_pass(np.ones((3, 3)), np.eye(3), np.empty((3, 3)))
    P, d = np.zeros((3, 2, 3)), np.ones(3)
    P[:, 0, 0] = P[:, 1, 1] = 1.0
    multilaterate(np.zeros(3), P, Y, d, d, 1)
    row_misfits(np.zeros(3), P, Y, d, np.array([0, 3]))
    _warm = True
