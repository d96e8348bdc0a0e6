"""Three-way SMACOF for the 3DMPE stress: an mpe3d solver plug-in.

The method a reviewer of 3DMPE would ask for first. The paper's stress

    S(X, P) = sum_k sum_{i<j} a_i^k a_j^k (D^k_ij - ||P^k (x_i - x_j)||)^2

is a three-way (individual-differences) MDS stress: one common 3D
configuration X, seen by each view k through its own rank-2 map P^k (as
IDIOSCAL gives each source its own linear map of the common space), with
zero weight on the pairs a view does not see. SMACOF minimises such a
stress by majorization (de Leeuw, "Applications of convex analysis to
multidimensional scaling", 1977; Borg and Groenen, "Modern Multidimensional
Scaling", 2005, ch. 8 and 12); every step lowers the stress:

- the X step is the Guttman transform of the three-way stress: with the
  projections fixed, the majorizer is the quadratic form sum_k tr(X^T V_k X M_k)
  with M_k = P^k^T P^k, whose minimiser solves H vec(X) = sum_k vec(B_k(Z) Z M_k).
  H is sparse in structure and is applied without being formed; the system is
  solved by block-Jacobi preconditioned conjugate gradients, warm-started;
- the P step (variable setting) majorizes each view's own stress in its 2D
  image: the Guttman transform of the view's current image is the target,
  and the best orthonormal P^k onto it is an orthogonal Procrustes fit.

The start is classical MDS of the views' averaged distances, unseen pairs
completed by shortest paths (the paper's baseline), and each free projection
is fitted to it. The method is not exact on noise-free views (majorization
converges linearly), and says so: it is registered without ``exact``.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import shortest_path
from scipy.sparse.linalg import LinearOperator, cg
from scipy.spatial.distance import cdist

import mpe3d
from mpe3d import Interval, Reconstruction

__version__ = "0.1.0"


def _views(observations):
    return [(np.asarray(v.ids), v.distance_matrix()) for v in observations.views]


def _start(n: int, views) -> np.ndarray:
    """Classical MDS of the averaged distances; unseen pairs by shortest paths."""
    total, count = np.zeros((n, n)), np.zeros((n, n))
    for ids, D in views:
        ix = np.ix_(ids, ids)
        total[ix] += D
        count[ix] += 1
    seen = count > 0
    average = np.where(seen, total / np.maximum(count, 1), 0.0)
    complete = shortest_path(csr_matrix(average), directed=False)
    finite = np.isfinite(complete)
    complete[~finite] = complete[finite].max() if finite.any() else 1.0
    J = np.eye(n) - 1.0 / n
    w, V = np.linalg.eigh(-0.5 * J @ complete**2 @ J)
    return V[:, -3:] * np.sqrt(np.maximum(w[-3:], 0.0))


def _procrustes(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The 2x3 map with orthonormal rows taking centred ``source`` closest to ``target``."""
    U, _, Vt = np.linalg.svd((source - source.mean(0)).T @ (target - target.mean(0)),
                             full_matrices=False)
    return (U @ Vt).T


def _stress(X, P, views) -> float:
    total = 0.0
    for (ids, D), Pk in zip(views, P):
        Y = X[ids] @ Pk.T
        total += 0.5 * float(np.sum((D - cdist(Y, Y)) ** 2))
    return total


def _b_matrix(Y: np.ndarray, D: np.ndarray) -> np.ndarray:
    """SMACOF's B(Y) for one view's 2D image Y: -D_ij / d_ij off the diagonal."""
    d = cdist(Y, Y)
    ratio = np.divide(D, d, out=np.zeros_like(D), where=d > 1e-300)
    B = -ratio
    B[np.diag_indices_from(B)] = ratio.sum(axis=1)
    return B


def _normal_parts(P, views, n: int):
    """What H takes from the projections: M_k = P^k^T P^k, the visibility as a
    K x n matrix, each point's own 3x3 block sum_k n_k M_k, and the inverse of
    H's diagonal blocks sum_k (n_k - 1) M_k (the block-Jacobi preconditioner).
    Fixed projections give them once for every X step."""
    M = np.transpose(P, (0, 2, 1)) @ P
    seen = np.zeros((len(views), n))
    for k, (ids, _) in enumerate(views):
        seen[k, ids] = 1.0
    own = np.einsum("kn,k,kij->nij", seen, seen.sum(axis=1), M)
    diagonal = own - np.einsum("kn,kij->nij", seen, M)
    return M, seen, own, np.linalg.pinv(diagonal + np.eye(3) / n**2, hermitian=True)


def _x_step(X, P, views, n: int, tol: float, parts=None) -> np.ndarray:
    """The three-way Guttman transform: solve H vec(X') = sum_k vec(B_k(X) X M_k)."""
    M, seen, own, inverse = parts if parts is not None else _normal_parts(P, views, n)
    rhs = np.zeros_like(X)
    for (ids, D), Pk, Mk in zip(views, P, M):
        rhs[ids] += (_b_matrix(X[ids] @ Pk.T, D) @ X[ids]) @ Mk

    def apply(v: np.ndarray) -> np.ndarray:
        # sum_k over the views' points of (n_k V - 1 1^T V) M_k, every view at once
        V = v.reshape(n, 3)
        out = np.einsum("nij,nj->ni", own, V) - seen.T @ np.einsum("kj,kji->ki", seen @ V, M)
        return (out + V.mean(axis=0) / n).ravel()  # the mean term pins the translation

    operator = LinearOperator((3 * n, 3 * n), matvec=apply, dtype=float)
    precondition = LinearOperator((3 * n, 3 * n), dtype=float,
                                  matvec=lambda v: np.einsum("nij,nj->ni", inverse, v.reshape(n, 3)).ravel())
    rhs -= rhs.mean(axis=0)
    solution, _ = cg(operator, rhs.ravel(), x0=(X - X.mean(0)).ravel(), rtol=tol, atol=0.0,
                     maxiter=10 * n, M=precondition)
    return solution.reshape(n, 3)


def _p_step(X, P, views) -> np.ndarray:
    """Each view's projection, by majorizing its stress in P.

    In the view's image Y = X_k P^T the stress is majorized by
    n ||Y_c - T||^2 with T = B(Y~) Y~ / n (the Guttman target). Its quadratic
    part tr(P S P^T), S = X_kc^T X_kc, is not constant over orthonormal P, so it
    is majorized in turn by its tangent plus lambda_max(S) ||P - P~||^2; what
    is left is linear in P, maximised by the polar factor of
    G = lambda P~^T - S P~^T + X_kc^T T. Each step lowers the view's stress.
    """
    out = []
    for (ids, D), Pk in zip(views, P):
        Xc = X[ids] - X[ids].mean(axis=0)
        Y = Xc @ Pk.T
        target = _b_matrix(Y, D) @ Y / len(ids)
        S = Xc.T @ Xc
        G = np.linalg.eigvalsh(S)[-1] * Pk.T - S @ Pk.T + Xc.T @ target
        U, _, Vt = np.linalg.svd(G, full_matrices=False)
        out.append((U @ Vt).T)
    return np.array(out)


@mpe3d.register_solver(
    "smacof3",
    constraints={"max_iter": Interval(int, 1, None), "tol": Interval(float, 0, 1, closed="left")},
    summary="three-way SMACOF: majorization of the 3DMPE stress (IDIOSCAL-style rank-2 views)")
def smacof3(observations, *, random_state, max_iter: int = 300, tol: float = 1e-6):
    """Minimise the 3DMPE stress (Eq. 1) by three-way SMACOF.

    Parameters
    ----------
    observations : mpe3d.Observations
        The views, and the projections in the fixed setting.
    random_state : numpy.random.Generator
        Unused: the method is deterministic (the start is classical MDS).
    max_iter : int, default 300
        Majorization steps at most (an X step, and a P step when variable).
    tol : float, default 1e-6
        Stop when a step lowers the stress by less than this share of it.
    """
    n, views = observations.n_points, _views(observations)
    X = _start(n, views)
    P = np.array([_procrustes(X[ids], mpe3d.View(ids, D).image()) for ids, D in views])
    X, P, history, termination = _majorize(X, P, views, max_iter, tol, free=True)
    if observations.fixed:  # turned onto the given views, then majorized with them
        given = np.asarray(observations.projections, dtype=float)
        X = X @ _turn(P, given).T
        X, P, more, termination = _majorize(X, given, views, max_iter, tol, free=False)
        history = history + more[1:]
    return Reconstruction(points=X, projections=P, stress=None, stress_history=np.array(history),
                          iterations=len(history) - 1, termination=termination)


def _majorize(X, P, views, max_iter: int, tol: float, free: bool):
    """SMACOF steps until a step gains less than ``tol`` of the stress."""
    history = [_stress(X, P, views)]
    parts = None if free else _normal_parts(P, views, len(X))
    for _ in range(max_iter):
        X = _x_step(X, P, views, len(X), tol=1e-10, parts=parts)
        if free:
            P = _p_step(X, P, views)
        history.append(_stress(X, P, views))
        if history[-2] - history[-1] <= tol * history[-2]:
            return X, P, history, f"stress decrease below tol={tol:g}"
    return X, P, history, f"max_iter={max_iter} reached"


def _turn(free: np.ndarray, given: np.ndarray, rounds: int = 50) -> np.ndarray:
    """The Q in O(3) that takes the free solution's frame to the given views'.

    Distances fix each view's image only up to its own O(2) motion R_k, so Q
    and the R_k are found together: P_free_k = R_k P_given_k Q, alternately
    for the R_k (each a 2x2 Procrustes) and for Q (one 3x3 Procrustes).
    The alternation has local optima, so it starts from the 48 frames of a
    cube (its 24 rotations, each also mirrored) and keeps the best.
    """
    best, best_gap = np.eye(3), np.inf
    for Q in _cube_frames():
        for _ in range(rounds):
            R = _polar(free @ Q.T @ np.transpose(given, (0, 2, 1)))  # every view's R_k at once
            Q = _polar(np.einsum("kai,kaj->ij", R @ given, free))
        gap = float(np.sum((free - R @ given @ Q) ** 2))
        if gap < best_gap:
            best, best_gap = Q, gap
    return best


def _cube_frames() -> list[np.ndarray]:
    """The 48 signed permutation matrices: every proper and mirrored cube frame."""
    from itertools import permutations, product

    return [np.eye(3)[list(order)] * np.array(signs)
            for order in permutations(range(3)) for signs in product((1, -1), repeat=3)]


def _polar(A: np.ndarray) -> np.ndarray:
    """The orthogonal polar factor of A (or of each matrix in a stack)."""
    U, _, Vt = np.linalg.svd(A)
    return U @ Vt
