"""Small dense linear algebra shared by the solvers."""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import LinearOperator, eigsh


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
