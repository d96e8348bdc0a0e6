"""Small dense linear algebra shared by the solvers."""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import eigsh


def classical_mds(D: np.ndarray, dim: int, random_state=None) -> np.ndarray:
    """Torgerson MDS: top-``dim`` eigenvectors of -J D^2 J / 2, by Lanczos."""
    n = len(D)
    B = -0.5 * D ** 2
    B -= B.mean(axis=0)
    B -= B.mean(axis=1)[:, None]
    if n <= dim + 1:
        vals, vecs = np.linalg.eigh(B)
        vals, vecs = vals[::-1][:dim], vecs[:, ::-1][:, :dim]
    else:
        rng = np.random.default_rng(random_state)
        vals, vecs = eigsh(B, k=dim, which="LA", v0=rng.standard_normal(n))
        order = np.argsort(vals)[::-1]
        vals, vecs = vals[order], vecs[:, order]
    X = vecs * np.sqrt(np.maximum(vals, 0.0))
    if X.shape[1] < dim:
        X = np.hstack([X, np.zeros((n, dim - X.shape[1]))])
    return X
