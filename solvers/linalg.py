"""Small dense linear algebra shared by the solvers."""

from __future__ import annotations

import numpy as np

# A PSD matrix with det > this x trace^d has condition number below 1 / this:
# inverted directly; the rest (rank-deficient, or nearly) by SVD.
_WELL_CONDITIONED = 1e-8


def pinv_psd(M: np.ndarray) -> np.ndarray:
    """``np.linalg.pinv`` of a stack of small symmetric positive semi-definite
    matrices (normal equations), by LU inversion where the matrix is well
    conditioned and by SVD where it is not: the same result to rounding, 10-15x
    faster on a million 3x3 systems. lambda_min / lambda_max >= det / trace^d
    for PSD matrices, so the test is a cheap and safe bound."""
    d = M.shape[-1]
    trace = np.trace(M, axis1=-2, axis2=-1)
    good = np.linalg.det(M) > _WELL_CONDITIONED * trace ** d
    if good.all():
        return np.linalg.inv(M)
    out = np.empty_like(M)
    out[good] = np.linalg.inv(M[good])
    out[~good] = np.linalg.pinv(M[~good])
    return out


def matvec_by_group(M: np.ndarray, group: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """out[t] = M[group[t]] @ Y[t] for a few matrices M (G, a, b) and many rows
    Y (T, b): one matrix product per group (a view, usually) instead of T
    small ones, and no (T, a, b) gather."""
    out = np.empty((len(Y), M.shape[1]), dtype=np.result_type(M, Y))
    for g, rows in enumerate(rows_by_group(group, len(M))):
        if len(rows):
            out[rows] = Y[rows] @ M[g].T
    return out


def rows_by_group(group: np.ndarray, n_groups: int) -> list[np.ndarray]:
    """Each group's rows, in increasing order (``np.flatnonzero(group == g)``
    for g < n_groups), by one stable sort: not a scan of every row per group
    (250 views x 138,000 observations: 16 ms a projection, now 6)."""
    order = np.argsort(group, kind="stable")
    ends = np.cumsum(np.bincount(group, minlength=n_groups))[:n_groups]
    return np.split(order[:ends[-1]], ends[:-1]) if n_groups else []


def gram_by_group(A: np.ndarray, group: np.ndarray, n_groups: int, B: np.ndarray | None = None):
    """sum over the rows t of each group of A_t^T B_t (A_t, B_t: rows, or (r, c)
    blocks flattened to r rows), one matrix product per group: (G, a, b)."""
    B = A if B is None else B
    A2, B2 = A.reshape(len(A), -1, A.shape[-1]), B.reshape(len(B), -1, B.shape[-1])
    out = np.zeros((n_groups, A2.shape[-1], B2.shape[-1]))
    for g, rows in enumerate(rows_by_group(group, n_groups)):
        if len(rows):
            out[g] = A2[rows].reshape(-1, A2.shape[-1]).T @ B2[rows].reshape(-1, B2.shape[-1])
    return out


def classical_mds(D: np.ndarray, dim: int, random_state=None) -> np.ndarray:
    """Torgerson MDS: top-``dim`` eigenvectors of B = -J D^2 J / 2, by Lanczos.

    B is applied as an operator (J centres a vector in O(n)), so the only
    n x n array made is D^2, the size of the input.
    """
    n = len(D)
    D2 = np.multiply(D, D)
    if n <= dim + 1:
        B = -0.5 * (D2 - D2.mean(axis=0) - D2.mean(axis=1)[:, None] + D2.mean())
        vals, vecs = np.linalg.eigh(B)
        vals, vecs = vals[::-1][:dim], vecs[:, ::-1][:, :dim]
    else:
        def apply(v):
            v = v.reshape(n, -1)
            w = D2 @ (v - v.mean(axis=0))
            return -0.5 * (w - w.mean(axis=0))

        from scipy.sparse.linalg import LinearOperator, eigsh  # here: only MDS needs them

        B = LinearOperator((n, n), matvec=apply, matmat=apply, dtype=float)
        rng = np.random.default_rng(random_state)
        # A small Krylov basis: the top eigenvalues of B stand far above the
        # rest (exactly rank `dim` without noise), so a few steps converge.
        vals, vecs = eigsh(B, k=dim, which="LA", v0=rng.standard_normal(n),
                           ncv=min(n, 2 * dim + 4))
        order = np.argsort(vals)[::-1]
        vals, vecs = vals[order], vecs[:, order]
    X = vecs * np.sqrt(np.maximum(vals, 0.0))
    if X.shape[1] < dim:
        X = np.hstack([X, np.zeros((n, dim - X.shape[1]))])
    return X


def elongation(X: np.ndarray) -> float:
    """The cloud's longest principal extent over its second: huge when a flat
    direction of the problem (depth under a small baseline, or a direction
    the noisy views all but miss) has run away."""
    extents = np.ptp((X - X.mean(axis=0)) @ np.linalg.svd(X - X.mean(axis=0),
                                                         full_matrices=False)[2].T, axis=0)
    return float(extents[0] / max(extents[1], 1e-300))


def stacked(obs, images: list[np.ndarray]):
    """Every observation (view k, point id, 2D point) as flat arrays."""
    view = np.concatenate([np.full(v.size, k) for k, v in enumerate(obs.views)])
    point = np.concatenate([v.ids for v in obs.views])
    z = np.concatenate(images)
    return view, point, z


def sum_by(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """Sum rows of ``values`` (T x ...) into ``size`` bins by ``index``."""
    flat = values.reshape(len(values), -1)
    out = np.stack([np.bincount(index, weights=flat[:, c], minlength=size)
                    for c in range(flat.shape[1])], axis=1)
    return out.reshape((size,) + values.shape[1:])


def fit_views(X, view, point, z, K, rows):
    """[L_k; t_k^T] from [x_i, 1] -> z_t over the observations in ``rows``: one 4x4
    least-squares system per view (views with no such rows come back zero)."""
    A = np.concatenate([X[point[rows]], np.ones((rows.sum(), 1))], axis=1)
    AtA = gram_by_group(A, view[rows], K)
    Atz = gram_by_group(A, view[rows], K, z[rows])
    Lt = np.einsum("kab,kbc->kac", pinv_psd(AtA), Atz)  # (K, 4, 2)
    return Lt[:, :3, :], Lt[:, 3, :]


def rows_of(view_ids, zk, ids):
    """Rows of one view's 2D points ``zk`` (of the points ``view_ids``) for the ids ``ids``."""
    order = np.argsort(view_ids)
    return zk[order[np.searchsorted(view_ids, ids, sorter=order)]]
