"""Starting points shared by the solvers: the averaged-distance MDS embedding
and the projections that best fit an embedding.

Paper, Section "Baseline Approach": average the K pairwise distance
matrices (:func:`average_distances`), complete the pairs no view sees by
graph distances (:func:`complete_distances`) and embed the result in 3D with
MDS (:func:`mds_embedding`). The baseline solver returns that embedding; SGD's
"smart" initialisation starts from it, with :func:`fit_projections` in the
variable setting.
"""

from __future__ import annotations

import numpy as np

from mpe3d.solvers import kernels, point_kernels
from mpe3d.solvers.base import Observations, require_memory
from mpe3d.solvers.linalg import classical_mds
from mpe3d.solvers.stress import project_rows

# Neighbours per point in the graph that fills pairs never seen together.
_GRAPH_NEIGHBOURS = 10


def average_distances(obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Mean of D^k_ij over the views where both i and j are visible.

    Returns the ``(N, N)`` average and the count of views that saw each pair.
    """
    N = obs.n_points
    require_memory(6 * 8 * N * N, f"points={N}: the baseline's dense {N}x{N} distance matrices")
    total = np.zeros((N, N))
    count = np.zeros((N, N), dtype=np.int32)
    for view in obs.views:  # the views' sums in their order, as np.ix_ updates made them
        point_kernels.add_view_distances(total, count, np.ascontiguousarray(view.ids, dtype=np.int64),
                                   np.ascontiguousarray(view.distance_matrix(), dtype=np.float64))
    np.divide(total, count, out=total, where=count > 0)
    return total, count


def complete_distances(D: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Fill the pairs no view saw together with graph (geodesic) distances.

    A pair that no view shows has no distance to average. We estimate it, as
    Isomap does, by the shortest path through each point's 10 nearest seen
    neighbours; pairs that even the graph cannot join (a point seen in no view)
    get the largest distance observed. Zero-filling, as the authors' code does,
    would pull unrelated points together.
    """
    np.fill_diagonal(seen, True)
    if seen.all():
        return D
    N = len(D)
    near = np.where(seen, D, np.inf)
    np.fill_diagonal(near, np.inf)
    k = min(_GRAPH_NEIGHBOURS, N - 1)
    nbr = np.argpartition(near, k - 1, axis=1)[:, :k]
    w = near[np.arange(N)[:, None], nbr]
    from scipy.sparse import csr_matrix  # here: a keypoint or photo solve never fills gaps (0.26 s of imports)
    from scipy.sparse.csgraph import shortest_path

    ok = np.isfinite(w)
    rows = np.repeat(np.arange(N), k)[ok.ravel()]
    graph = csr_matrix((np.maximum(w[ok], 1e-12), (rows, nbr[ok])), shape=(N, N))
    sources = np.flatnonzero((~seen).any(axis=1))
    geo = shortest_path(graph, method="D", directed=False, indices=sources)
    out = D.copy()
    fill = out[sources]
    np.copyto(fill, geo, where=~seen[sources])
    out[sources] = fill
    out = np.minimum(out, out.T)  # the geodesic from either end
    finite = np.isfinite(out)
    if not finite.all():
        out[~finite] = out[finite].max() if finite.any() else 1.0
    return out


def fit_projections(X: np.ndarray, obs: Observations, random_state=None) -> np.ndarray:
    """Projections P^k (orthonormal rows) that best map X to each view's MDS image.

    Each view's 2D points are recovered by classical MDS up to an O(2)
    transform; the orthogonal Procrustes problem min ||Z_k - X_k P^T|| over
    P P^T = I then gives a starting projection. Used for the variable setting.
    """
    P = np.zeros((obs.n_views, 2, 3))
    for k, view in enumerate(obs.views):
        Z = view.image(random_state)
        Xk = X[view.ids] - X[view.ids].mean(axis=0)
        U, _, Vt = np.linalg.svd(Xk.T @ Z, full_matrices=False)  # (3x2)
        P[k] = (U @ Vt).T
    return project_rows(P)


def authors_average(obs: Observations) -> np.ndarray:
    """The authors' code's average: each view's N x N matrix with zeros for the
    pairs it does not see, summed and divided by K."""
    total, count = average_distances(obs)
    return total * count / obs.n_views


def mds_embedding(obs: Observations, method: str = "smacof", max_iter: int = 300,
                  random_state=None) -> np.ndarray:
    """The baseline's 3D embedding of the averaged, completed distance matrix
    (``method="authors"``: of the authors' zero-filled average, by SMACOF)."""
    if method == "authors":
        D = authors_average(obs)
    else:
        D, count = average_distances(obs)
        D = complete_distances(D, count > 0)
    X = classical_mds(D, 3, random_state)
    if method in ("smacof", "authors"):
        # scikit-learn's metric SMACOF (what the paper ran), step for step, in one
        # compiled pass an iteration: 7x faster at N=1024, and the same iterates.
        X, _, _ = kernels.smacof(D, X, max_iter=max_iter)
    return X
