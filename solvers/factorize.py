"""``factorize``: the point cloud from the views by linear algebra, no iterations on the stress.

Noise-free views determine the cloud exactly, up to a rigid motion and a mirror
image, and this solver recovers it to machine precision:

1. Each view's 2D points z_i^k come from classical MDS of D^k (top two
   eigenvectors by Lanczos), or from the given coordinates; they equal
   P^k x_i up to an unknown O(2) transform and a translation.
2. Fixed projections: P^k x_i = H_k z_i^k + s_k is linear in (X, H, s).
   Eliminating X and s leaves a 4K x 4K quadratic form in the H_k whose
   smallest eigenvector gives them; each H_k is projected onto O(2) and X
   solved by least squares.
3. Variable projections: the affine factorisation z_i^k = L_k^T x_i + t_k with
   missing entries, by alternating least squares, then the metric upgrade (a
   symmetric M with L_k^T M L_k = I for every view, M = A A^T, X <- X A^-T),
   and each projection is orthonormalised.

Everything is O(sum_k n_k) after the per-view MDS, with one 3x3 system per
point; no N x N matrix is formed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mpe3d.solvers import point_kernels
from mpe3d.solvers.base import Interval, Observations, Reconstruction, register_solver
from mpe3d.solvers.degenerate import check_geometry, warn
from mpe3d.solvers.linalg import (
    elongation,
    fit_views,
    gram_by_group,
    matvec_by_group,
    pinv_psd,
    rows_of,
    stacked,
    sum_by,
)
from mpe3d.solvers.stress import Stress, project_rows

# Points per block of the fixed setting's elimination: keeps each (points, 3, 4K)
# block near 50 MB at K = 8, so a million points never hold N x 3 x 4K at once.
_POINT_BLOCK = 1 << 16


class _FixedLinearSystem:
    """X as a linear function of vec(H), X = Y(h), for the fixed setting.

    Minimises sum_t ||P^k x_i - s_k - H_k z_t||^2 over X and s: with
    M_i = sum P^kT P^k the normal equations read
    M_i x_i - sum_k P^kT P^k xbar_k = sum_t P^kT H_k z_t, the view means xbar_k
    eliminated through a small 3K x 3K system (singular along translations:
    its minimum-norm solution is used). Y_i (3 x 4K) is formed block by block
    of points, each time it is needed, instead of for all points at once.
    """

    def __init__(self, obs, view, point, z, P):
        self.K, self.N, self.P = obs.n_views, obs.n_points, P
        self.view, self.point, self.z = view, point, z
        self.PtP = np.einsum("kai,kaj->kij", P, P)
        self.M_inv = pinv_psd(sum_by(point, self.PtP[view], self.N))  # < 2 views: min-norm
        self.order = np.argsort(point, kind="stable")  # observations grouped by point block
        self.bounds = np.searchsorted(point[self.order],
                                      np.arange(0, self.N + _POINT_BLOCK, _POINT_BLOCK))
        alpha = obs.visibility().astype(float)
        sizes = alpha.sum(axis=1)
        b = np.zeros((self.K, 3 * 4 * self.K))  # xbar_k = mean over k's points of M_i^-1 (...)
        shared = np.zeros((self.K, self.K, 3, 3))  # sum of M_i^-1 over the points in k and l
        for lo, hi in self._blocks():
            base = self.M_inv[lo:hi] @ self._c(lo, hi)
            b += alpha[:, lo:hi] @ base.reshape(hi - lo, -1)
            shared += np.einsum("kn,ln,nij->klij", alpha[:, lo:hi], alpha[:, lo:hi], self.M_inv[lo:hi])
        b = b.reshape(self.K, 3, -1) / sizes[:, None, None]
        T = np.einsum("klij,ljm->kilm", shared, self.PtP) / sizes[:, None, None, None]
        system = np.eye(3 * self.K) - T.reshape(3 * self.K, 3 * self.K)
        means = np.linalg.lstsq(system, b.reshape(3 * self.K, -1), rcond=None)[0].reshape(self.K, 3, -1)
        self.pull = self.PtP @ means  # (K, 3, 4K): PtP_k xbar_k, what view k adds to each point
        self.alpha = alpha

    def _blocks(self):
        return [(lo, min(lo + _POINT_BLOCK, self.N)) for lo in range(0, self.N, _POINT_BLOCK)]

    def _c(self, lo, hi):
        """sum_t P^kT B_t for the points lo..hi, with B_t z-linear in vec(H_k):
        H_k z_t = (z_t^T kron I_2) vec(H_k), so the columns of view k are
        z0 P_k[0], z0 P_k[1], z1 P_k[0], z1 P_k[1] (one observation per point)."""
        rows = self.order[self.bounds[lo // _POINT_BLOCK]:self.bounds[lo // _POINT_BLOCK + 1]]
        c = np.zeros((hi - lo, 3, 4 * self.K))
        p, k, z = self.point[rows] - lo, self.view[rows], self.z[rows]
        for col, (a, r) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            c[p, :, 4 * k + col] = z[:, a, None] * self.P[k, r]
        return c

    def block(self, lo, hi):
        """(Y, C) for the points lo..hi: X_i = Y_i h, and C_i = sum_t P^kT B_t."""
        c = self._c(lo, hi)
        coupled = np.einsum("kn,kim->nim", self.alpha[:, lo:hi], self.pull)
        return self.M_inv[lo:hi] @ (c + coupled), c

    def quadratic_form(self):
        """Q = sum_t B_t^T B_t - sum_i C_i^T Y_i: the stress after eliminating X and s."""
        K = self.K
        Q = np.zeros((4 * K, 4 * K))
        zz = gram_by_group(self.z, self.view, K)  # (K, 2, 2): sum z z^T per view
        for k in range(K):  # B^T B is block diagonal: (z z^T) kron I_2 per view
            Q[4 * k:4 * k + 4, 4 * k:4 * k + 4] = np.kron(zz[k], np.eye(2))
        for lo, hi in self._blocks():
            Y, C = self.block(lo, hi)
            Q -= np.einsum("nim,nik->mk", C, Y)
        return Q

    def points(self, h):
        return np.concatenate([np.einsum("nim,m->ni", self.block(lo, hi)[0], h)
                               for lo, hi in self._blocks()])


# A 2x2 matrix c * O with O in O(2) is a*I + b*J (a rotation, det > 0) or a*F + b*G
# (a reflection): two planes in vec-space (column-major [H11, H21, H12, H22]).
_SIMILARITY = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [1.0, 0.0]])
_REFLECTION = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [-1.0, 0.0]])
_MAX_ENUMERATED_VIEWS = 12


def _orthogonal_transforms(Q: np.ndarray, K: int) -> np.ndarray:
    """The H_k in O(2) minimising h^T Q h (step 2), as (K, 2, 2).

    The unconstrained smallest eigenvector of Q is not enough: when the view
    directions are nearly coplanar, a stretch along their common normal is an
    almost-exact spurious solution with non-orthogonal H_k. Restricting each
    H_k to the rotation or the reflection plane removes it; which of the two
    each view needs (MDS may mirror a view) is found by trying all 2^K
    choices, each a 2K x 2K eigenproblem (beyond 12 views, the signs of the
    unconstrained solution's determinants choose).
    """
    if K <= _MAX_ENUMERATED_VIEWS:
        choices = np.array(np.meshgrid(*[[False, True]] * K, indexing="ij")).reshape(K, -1).T
    else:
        unconstrained = np.linalg.eigh(Q)[1][:, 0].reshape(K, 2, 2).transpose(0, 2, 1)
        choices = (np.linalg.det(unconstrained) < 0)[None, :]
    best = (np.inf, None, None)
    ranked = []
    for mirrored in choices:
        S = np.zeros((4 * K, 2 * K))
        for k, flip in enumerate(mirrored):
            S[4 * k:4 * k + 4, 2 * k:2 * k + 2] = _REFLECTION if flip else _SIMILARITY
        values, vectors = np.linalg.eigh(S.T @ Q @ S)
        ranked.append(values[0])
        if values[0] < best[0]:
            best = (values[0], S @ vectors[:, 0], values)
    _, h, values = best
    ranked = np.sort(ranked)
    runner_up = min(values[1], ranked[1] if len(ranked) > 1 else np.inf)
    if runner_up <= 1e-9 * max(abs(np.linalg.eigvalsh(Q)[-1]), 1e-300):
        warn("the views do not pin the shape down: more than one set of view transforms "
             "fits the data (too few points shared between views)")
    H = h.reshape(K, 2, 2).transpose(0, 2, 1)
    return H / np.sqrt(np.sum(H ** 2, axis=(1, 2)) / 2)[:, None, None]  # unit scale, as MDS


def factorize_fixed(obs: Observations, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """X and the per-view O(2) transforms H_k, fixed projections (step 2)."""
    K = obs.n_views
    P = np.asarray(obs.projections, dtype=float)
    view, point, z = stacked(obs, images)
    system = _FixedLinearSystem(obs, view, point, z, P)  # X as a linear function of vec(H)
    Q = system.quadratic_form()
    H = _orthogonal_transforms((Q + Q.T) / 2, K)
    return system.points(H.transpose(0, 2, 1).reshape(-1)), H


def _fit_points(L, t, view, point, z, N, rows):
    """(sum L_k L_k^T) x_i = sum L_k (z_t - t_k) over ``rows``: a 3x3 system per point."""
    v, p = view[rows], point[rows]
    lhs = sum_by(p, np.einsum("kab,kcb->kac", L, L)[v], N)  # L_k L_k^T: once per view
    rhs = sum_by(p, matvec_by_group(L, v, z[rows] - t[v]), N)
    return np.einsum("nij,nj->ni", pinv_psd(lhs), rhs)


def _affine_start(view, point, z, N, K):
    """An affine reconstruction grown from the two views sharing most points.

    Two affine views fix the affine structure of the points they share (a
    rank-3 factorisation of their centred 4 x m coordinates); every other view
    is then resected from 4+ placed points and every point triangulated from
    2+ placed views, until nothing more can be placed. Noise-free, this is
    already the exact affine solution, so the alternating least squares that
    follow only polish; from a random start they can stall.
    """
    alpha = np.zeros((K, N), dtype=bool)
    alpha[view, point] = True
    shared = alpha.astype(np.int32) @ alpha.T.astype(np.int32)
    np.fill_diagonal(shared, -1)
    a, b = np.unravel_index(np.argmax(shared), shared.shape)
    common = np.flatnonzero(alpha[a] & alpha[b])
    W = np.hstack([rows_of(point[view == k], z[view == k], common) for k in (a, b)])
    W = W - W.mean(axis=0)
    U, S, Vt = np.linalg.svd(W, full_matrices=False)
    X = np.zeros((N, 3))
    X[common] = U[:, :3] * S[:3]
    placed = np.zeros(N, dtype=bool)
    placed[common] = True
    registered = np.zeros(K, dtype=bool)
    registered[[a, b]] = True
    while True:
        L, t = fit_views(X, view, point, z, K, placed[point])
        seen = np.bincount(view[placed[point]], minlength=K)
        registered |= seen >= 4
        in_registered = registered[view]
        reach = np.bincount(point[in_registered], minlength=N)
        grow = ~placed & (reach >= 2)
        if not grow.any():
            return X
        X[grow] = _fit_points(L, t, view, point, z, N, in_registered)[grow]
        placed |= grow


class AffineFit(NamedTuple):
    """Affine structure and motion: points, each view's L_k (3x2), the RMS of the
    fit and the sweeps it took."""

    X: np.ndarray
    L: np.ndarray
    rms: float
    sweeps: int


def affine_als(view, point, z, N: int, K: int, max_iter: int, tol: float) -> AffineFit:
    """z_t ~ L_k^T x_i + t_k with missing data, by alternating least squares
    (one compiled pass a sweep, :func:`point_kernels.affine_als`), from
    :func:`_affine_start`, for the observations t = (view[t], point[t], z[t])
    of N points in K views."""
    X = _affine_start(view, point, z, N, K)
    # A point seen once says nothing about the views: it fits any of them.
    informative = np.bincount(point, minlength=N)[point] >= 2
    X, L, rms, sweeps = point_kernels.affine_als(
        np.ascontiguousarray(view, dtype=np.int64), np.ascontiguousarray(point, dtype=np.int64),
        np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(X, dtype=np.float64),
        informative, K, max_iter, tol, 1e-14 * _scale(z))
    return AffineFit(X, L, float(rms), int(sweeps))


def _scale(z: np.ndarray) -> float:
    return float(np.sqrt(np.mean(z ** 2))) or 1.0


_UPPER = np.triu_indices(3)
_HALVE = np.where(_UPPER[0] == _UPPER[1], 2.0, 1.0)


def _bilinear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a_k^T M b_k for each row k, as coefficients of M's upper triangle (symmetric M)."""
    outer = np.einsum("ki,kj->kij", a, b)
    return (outer + outer.transpose(0, 2, 1))[:, _UPPER[0], _UPPER[1]] / _HALVE


def _symmetric(m: np.ndarray) -> np.ndarray:
    """The symmetric 3x3 matrix with upper triangle ``m``."""
    M = np.zeros((3, 3))
    M[_UPPER] = m
    return M + M.T - np.diag(np.diag(M))


def metric_upgrade(X: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From an affine to a metric reconstruction (step 3).

    Finds the symmetric M with l1^T M l1 = l2^T M l2 = 1 and l1^T M l2 = 0 for
    every view (linear least squares in its 6 entries), writes M = A A^T and
    returns X A^-T and the projections A^T L_k, orthonormalised. Noise can make
    the linear M indefinite; then A comes from :func:`metric_upgrade_pd`,
    positive definite by construction, instead of clipping M's negative
    eigenvalues (which stretched the cloud to 10^6 times its size).
    """
    l1, l2 = L[:, :, 0], L[:, :, 1]
    system = np.concatenate([_bilinear(l1, l1), _bilinear(l2, l2), _bilinear(l1, l2)])
    target = np.concatenate([np.ones(len(L)), np.ones(len(L)), np.zeros(len(L))])
    m, _, rank, _ = np.linalg.lstsq(system, target, rcond=None)
    if rank < 6 and len(L) > 2:  # with 2 views, check_geometry has said so already
        warn(f"the metric upgrade is ambiguous (rank {rank} of 6): the views' directions "
             "do not fix the shape's proportions")
    values, vectors = np.linalg.eigh(_symmetric(m))
    if values[0] > 0:
        A = vectors * np.sqrt(values)
    else:
        A = metric_upgrade_pd(L)
        rows = np.einsum("ia,kib->kba", A, L)
        A = A / np.sqrt(np.mean(np.sum(rows ** 2, axis=(1, 2)) / 2))  # unit-length rows
    X = X @ np.linalg.inv(A).T
    P = project_rows(np.einsum("ia,kib->kba", A, L))
    return X, P


def metric_upgrade_pd(L: np.ndarray) -> np.ndarray:
    """A (3x3, invertible) with L_k^T A A^T L_k = s_k^2 I as nearly as possible.

    Weak perspective: each view's two camera rows (columns of L_k) are
    orthogonal and of equal length under M = A A^T. A is lower-triangular and
    fitted by least squares, so M is positive definite by construction, unlike
    the linear solution, which noise or a perspective camera can make
    indefinite (and the cloud then blows up along the clipped direction).
    """
    l1, l2 = L[:, :, 0], L[:, :, 1]
    rows, cols = np.tril_indices(3)

    def terms(a):
        A = np.zeros((3, 3))
        A[rows, cols] = a
        u, v = l1 @ A, l2 @ A
        p, q, r = np.sum(u * u, 1), np.sum(v * v, 1), np.sum(u * v, 1)
        return A, u, v, p, q, r, p + q + 1e-300

    def residual(a):
        A, _, _, p, q, r, total = terms(a)
        return np.concatenate([(p - q) / total, 2 * r / total, [np.log(np.abs(np.diag(A))).sum()]])

    def jacobian(a):
        # analytic: with finite differences the fit took 600 evaluations on 100 views
        _, u, v, p, q, r, total = terms(a)
        dp, dq = 2 * u[:, cols] * l1[:, rows], 2 * v[:, cols] * l2[:, rows]  # (K, 6)
        dr = u[:, cols] * l2[:, rows] + v[:, cols] * l1[:, rows]
        dt = (dp + dq) / total[:, None]
        diagonal = np.where(rows == cols, 1 / np.where(rows == cols, a, 1.0), 0.0)
        return np.vstack([(dp - dq) / total[:, None] - ((p - q) / total)[:, None] * dt,
                          2 * dr / total[:, None] - (2 * r / total)[:, None] * dt, diagonal])

    starts = [np.eye(3)[rows, cols]]
    linear = _linear_upgrade(L)
    if linear is not None:
        starts.insert(0, linear[rows, cols])
    from scipy.optimize import least_squares  # here: scipy.optimize costs 0.1 s to import

    method = "lm" if 2 * len(L) + 1 >= 6 else "trf"  # lm needs as many residuals as unknowns
    best = min((least_squares(residual, a0, jac=jacobian, method=method, xtol=1e-15,
                              ftol=1e-15, gtol=1e-15) for a0 in starts), key=lambda r: r.cost)
    A = np.zeros((3, 3))
    A[rows, cols] = best.x
    return A


def _linear_upgrade(L: np.ndarray) -> np.ndarray | None:
    """The Cholesky factor of the linear least-squares M, when it is positive definite."""
    l1, l2 = L[:, :, 0], L[:, :, 1]
    p, q = _bilinear(l1, l1), _bilinear(l2, l2)
    # equal lengths and orthogonal rows, and the mean squared length fixed to 1
    system = np.concatenate([p - q, _bilinear(l1, l2), (p + q).mean(0, keepdims=True)])
    target = np.zeros(len(system))
    target[-1] = 2.0
    m = np.linalg.lstsq(system, target, rcond=None)[0]
    try:
        return np.linalg.cholesky(_symmetric(m))
    except np.linalg.LinAlgError:
        return None


# Views whose directions leave a blind one: sum_k ||P^k d||^2 below this share of K
# for some unit d. Real views never do; a noisy affine fit drifting to a
# near-planar cloud does, and its metric cloud is then stretched along d.
_BLIND = 1e-3
_FALLBACK_SWEEPS = (20, 5, 1)
_ELONGATED = 20.0  # longest over second principal extent: no bundled shape passes 5


def blindness(P: np.ndarray) -> float:
    """min over unit d of sum_k ||P^k d||^2 / K: 0 when the views share a blind direction."""
    return float(np.linalg.eigvalsh(np.einsum("kai,kaj->ij", P, P))[0]) / len(P)


def _variable(observations, images, max_iter, tol):
    """The variable setting (step 3), with a checked fallback: when noise lets the
    alternating sweeps drift to a cloud that all upgraded views see edge-on,
    fewer sweeps are tried, and if none helps it is said. The last value says
    whether a cloud passed the check."""
    view, point, z = stacked(observations, images)
    tried = []
    for sweeps in (max_iter,) + tuple(s for s in _FALLBACK_SWEEPS if s < max_iter):
        X, L, rms, done = affine_als(view, point, z, observations.n_points,
                                     observations.n_views, sweeps, tol)
        X, P = metric_upgrade(X, L)
        if blindness(P) >= _BLIND and elongation(X) <= _ELONGATED:
            return X, P, rms, done, True
        tried.append((X, P, rms, done))
    # none passed: the least degenerate, said (seeing every direction first, then the roundest)
    X, P, rms, done = max(tried, key=lambda c: (blindness(c[1]) >= _BLIND, -elongation(c[0])))
    if blindness(P) >= _BLIND:
        warn(f"the cloud is {elongation(X):.3g} times longer than wide: the views, too noisy for "
             "factorize, may not determine its long axis (refine starts from the MDS start "
             "instead on dense views)")
        return X, P, rms, done, False
    warn(f"the upgraded views all but share a blind direction (blindness {blindness(P):.2g}): the "
         "cloud is not determined along it; the views are too noisy for factorize (refine "
         "starts from the MDS start instead on dense views)")
    return X, P, rms, done, False


_PARAMETER_CONSTRAINTS = {
    "max_iter": Interval(int, 1, None),
    "tol": Interval(float, 0.0, None),
}


@register_solver("factorize", constraints=_PARAMETER_CONSTRAINTS, paper=False, exact=True,
          summary="ours: exact algebraic solution (per-view MDS, factorisation, metric upgrade)")
def solve_factorize(observations: Observations, *, random_state=None,
                    max_iter: int = 2000, tol: float = 1e-13) -> Reconstruction:
    """Algebraic 3DMPE: exact on noise-free views (see module doc).

    Parameters
    ----------
    max_iter : int, default 2000
        Alternating least-squares sweeps of the affine factorisation
        (variable setting only).
    tol : float, default 1e-13
        Stop the sweeps when the RMS residual improves by less than this
        fraction.

    There is no ``init``: nothing here depends on a starting point. The
    result has no iterations on the stress (``iterations`` is 0); the ALS
    sweeps are ``info["als_sweeps"]``.
    ``random_state`` seeds the Lanczos start vectors of the per-view MDS.
    """
    rng = np.random.default_rng(random_state)
    unplaced = check_geometry(observations)
    images = [view.image(rng) for view in observations.views]
    if observations.fixed:
        X, _ = factorize_fixed(observations, images)
        P = np.asarray(observations.projections, dtype=float)
        sweeps, termination, settled = 0, "closed form", True
    else:
        X, P, rms, sweeps, settled = _variable(observations, images, max_iter, tol)
        termination = f"affine factorisation, RMS residual {rms:.2e}"
    stress = Stress(observations).value(X, P)
    return Reconstruction(points=X, projections=P, stress=stress,
                          stress_history=np.array([stress]), iterations=0,
                          termination=termination, info={"unplaced": unplaced, "als_sweeps": sweeps,
                                "degenerate": not settled})
