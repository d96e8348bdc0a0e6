"""The 3DMPE stress (paper Eq. 1) and its gradient, one view at a time.

    S(X, P) = sum_k sum_{i>j} a_i^k a_j^k (D^k_ij - ||P^k x_i - P^k x_j||)^2

For one view with image points y_i = P^k x_i, write e_ij = ||y_i - y_j|| and
B_ij = w_ij (D_ij - e_ij) / e_ij (w is the minibatch mask, symmetric). Then

    dS/dy_i = -2 sum_j B_ij (y_i - y_j)   i.e.   G_Y = -2 (diag(B 1) - B) Y,

and the chain rule through Y = X_vis P^T gives G_X[vis] += G_Y P and
G_P = G_Y^T X_vis. The default ``kernel="compiled"`` evaluates a view in one
fused pass over its pairs i < j (:mod:`.kernels`), reading each input distance
once and making no n x n temporary. ``kernel="numpy"`` is the earlier
formulation, dense array work over row blocks of the view's distance matrix
(e from scipy's cdist), kept as the reference the compiled kernel is checked
and benchmarked against. With the paper's l2 loss, full batches and dense
views, the loop over views runs inside one compiled call too
(:func:`kernels.l2_views`, the same bits): on hundreds of small views the
Python around each view's call had cost twice the kernel.
"""

from __future__ import annotations

import copy

import numpy as np

from mpe3d.options import STRESS_LOSSES
from mpe3d.solvers import kernels, point_kernels
from mpe3d.solvers.base import Observations

# Rows per block: keeps each temporary at about 4M float64 entries (32 MB).
_BLOCK_ENTRIES = 1 << 22
# A view given as 2D coordinates with more points than this is scored on a
# sparse pair set instead of all pairs: no n x n array on the coordinates path.
DENSE_LIMIT = 4096
NEIGHBOURS = 8  # nearest neighbours per point in the view (local rigidity)
RANDOM_PAIRS = 8  # random partners per point (global rigidity)
# All views' distances are copied into one array for :func:`kernels.l2_views`
# up to this many entries in all (128 MB); beyond, each view is one kernel call,
# whose Python around it is then a negligible share of the view's pairs.
PACK_LIMIT = 1 << 24


def sparse_pairs(Y: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(i, j), i < j: each point's nearest neighbours in the view and random partners.

    On noise-free views the stress over these pairs is zero exactly where the
    all-pairs stress is, for any rigid graph; k-NN plus random edges is rigid
    with overwhelming probability.
    """
    n = len(Y)
    k = min(NEIGHBOURS, n - 1)
    from scipy.spatial import cKDTree  # here: scipy.spatial costs 0.14 s to import, keypoints never need it

    _, nn = cKDTree(Y).query(Y, k=k + 1)
    i = np.concatenate([np.repeat(np.arange(n), k), np.repeat(np.arange(n), RANDOM_PAIRS)])
    j = np.concatenate([nn[:, 1:].ravel(), rng.integers(0, n, size=n * RANDOM_PAIRS)])
    a, b = np.minimum(i, j), np.maximum(i, j)
    keep = a != b
    pairs = np.sort(a[keep].astype(np.int64) * n + b[keep])
    # sorted, then duplicates dropped: np.unique's hashing is 15x slower on these keys
    pairs = pairs[np.concatenate([[True], pairs[1:] != pairs[:-1]])]
    return pairs // n, pairs % n


def _view_inputs(observations: Observations) -> list:
    """Per view: its dense distance matrix, or (i, j, d) over a sparse pair set;
    made once per observations and dense limit, and shared by every Stress of
    them (a solver and its report build several, and the pair set of a million
    keypoints takes seconds)."""
    cache = observations.__dict__.setdefault("_stress_inputs", {})  # frozen: no setattr
    if DENSE_LIMIT not in cache:
        out = []
        rng = np.random.default_rng(0)  # the pair set is part of the objective: fixed
        for view in observations.views:
            if view.coordinates is not None and view.size > DENSE_LIMIT:
                i, j = sparse_pairs(view.coordinates, rng)
                out.append((i, j, np.linalg.norm(view.coordinates[i] - view.coordinates[j], axis=1)))
            else:
                out.append(np.ascontiguousarray(view.distance_matrix(), dtype=np.float64))
        cache[DENSE_LIMIT] = out
    return cache[DENSE_LIMIT]


KERNELS = ("compiled", "numpy")


def _loss(r: np.ndarray, loss: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(r) and phi(r) = rho'(r) / 2 per residual; both equal r^2 and r near 0,
    so a robust stress is the paper's stress for small residuals."""
    if loss == "huber":
        clipped = np.clip(r, -scale, scale)
        return np.where(np.abs(r) <= scale, r * r, 2 * scale * np.abs(r) - scale * scale), clipped
    root = np.sqrt(1.0 + (r / scale) ** 2)  # soft_l1
    return 2 * scale * scale * (root - 1.0), r / root


def _weighted_loss(r: np.ndarray, w: np.ndarray | None, loss: str, scale: float):
    """sum of w rho(r), and w phi(r) in place of r for the gradient (w = 1 if None)."""
    if loss == "l2":
        if w is None:
            flat = r.ravel()
            return float(flat @ flat), r
        wr = w * r
        return float(np.vdot(wr, r)), wr
    rho, phi = _loss(r, loss, scale)
    if w is None:
        return float(rho.sum()), phi
    return float(np.vdot(w, rho)), w * phi


class Stress:
    """Evaluate the stress and its gradients for fixed observations.

    ``loss="l2"`` is the paper's Eq. 1. ``huber`` and ``soft_l1`` replace each
    squared residual r^2 by rho(r), quadratic up to ``scale`` and linear beyond
    it, so that corrupted distances and wrong correspondences pull less.
    """

    def __init__(self, observations: Observations, loss: str = "l2", scale: float = 1.0,
                 kernel: str = "compiled"):
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        self.loss, self.scale, self.kernel = loss, float(scale), kernel
        self._loss_code = STRESS_LOSSES.index(loss)
        self.n_points = observations.n_points
        self.ids = [view.ids for view in observations.views]
        # Per view: a dense distance matrix, or (i, j, d) over a sparse pair set.
        inputs = _view_inputs(observations)
        self.D = [None if isinstance(x, tuple) else x for x in inputs]
        self.pairs = [x if isinstance(x, tuple) else None for x in inputs]
        self.n_pairs = sum(len(p[0]) if p else len(i) * (len(i) - 1) // 2
                           for i, p in zip(self.ids, self.pairs))
        self.alpha = [None] * len(self.ids)  # per view: a weight per visible point, or None
        self._kept = [None] * len(self.ids)  # per view: its points of weight > 0 (weighted)
        self._packed = self._one_call()  # the views as kernels.l2_views reads them

    def weighted(self, alpha: list) -> "Stress":
        """The same stress with each observation (view k, point i) weighted:
        the paper's visibility alpha_i^k of Eq. 1 taken from {0, 1} into [0, 1],
        each squared residual counting alpha_i^k alpha_j^k times. Shares the
        distances."""
        out = copy.copy(self)
        out.alpha = [None if a is None else np.ascontiguousarray(a, dtype=np.float64) for a in alpha]
        out._kept = [out._compact(k) for k in range(len(out.ids))]
        out._packed = out._one_call()
        return out

    def _sizes(self) -> list[int]:
        return [len(ids) if kept is None else len(kept[0]) for ids, kept in zip(self.ids, self._kept)]

    def _one_call(self):
        """None when :func:`kernels.l2_views` applies (made on first use), False
        when it does not: a robust loss, a sparse view, the numpy kernel, more
        than PACK_LIMIT distances in all."""
        fits = sum(n * n for n in self._sizes()) <= PACK_LIMIT
        return None if self.kernel == "compiled" and self.loss == "l2" and not self.sparse and fits \
            else False

    def _pack(self):
        """The views as one set of flat arrays for :func:`kernels.l2_views`, or False."""
        if self._packed is None:
            self._packed = self._flatten(self._sizes())
        return self._packed

    def _flatten(self, sizes):
        views = [kept or (np.zeros(0, dtype=np.int64), D, alpha)
                 for kept, D, alpha in zip(self._kept, self.D, self.alpha)]
        alpha = [np.zeros(0) if a is None else a for _, _, a in views]

        def starts(lengths):
            return np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)

        return (np.concatenate([D.ravel() for _, D, _ in views]), starts([n * n for n in sizes]),
                np.concatenate(self.ids).astype(np.int64), starts(list(map(len, self.ids))),
                np.concatenate([keep for keep, _, _ in views]).astype(np.int64),
                starts([len(keep) for keep, _, _ in views]),
                np.array([kept is not None for kept in self._kept]),
                np.concatenate(alpha).astype(np.float64), starts(list(map(len, alpha))))

    def _all_views(self, X, P, want_grad: bool, want_P: bool):
        """(S, dS/dX or None, dS/dP or None) by :func:`kernels.l2_views`."""
        gX = np.zeros((len(X) if want_grad else 0, 3))
        gP = np.zeros((len(P) if want_grad else 0, 2, 3))  # l2_views indexes it per view
        total = kernels.l2_views(np.ascontiguousarray(X, dtype=np.float64),
                                 np.ascontiguousarray(P, dtype=np.float64), *self._packed,
                                 want_grad, want_P, gX, gP)
        return total, gX if want_grad else None, gP if want_P else None

    def _compact(self, k: int):
        """View k without its points of weight 0, when it drops at least a tenth
        of them: (their positions, the distances among the rest, their weights
        or None if all 1). Every pair of a dropped point has weight 0, so the
        compiled kernel on the rest adds the same terms in the same order and
        skips only zeros, at a fraction of the pairs."""
        a = self.alpha[k]
        if a is None or self.pairs[k] is not None or self.kernel != "compiled":
            return None
        keep = np.flatnonzero(a > 0)
        if len(keep) > 0.9 * len(a):
            return None
        rest = a[keep]
        return keep, np.ascontiguousarray(self.D[k][np.ix_(keep, keep)]), \
            None if np.all(rest == 1.0) else np.ascontiguousarray(rest)

    def row_residuals(self, X: np.ndarray, P: np.ndarray, among: list) -> list[np.ndarray]:
        """Per view, each row's median |D_ij - ||P(x_i - x_j)||| over the points j
        ``among[k]`` (a boolean mask over the view's points): the size of the
        misfit of observation (k, i), which the rows it is compared with, if
        fewer than half of them are corrupted, do not sway. Dense views only;
        a sparse view gives zeros."""
        out = []
        for k, ids in enumerate(self.ids):
            if self.pairs[k] is not None or not np.any(among[k]):
                out.append(np.zeros(len(ids)))
                continue
            Y = X[ids] @ P[k].T
            cols = np.flatnonzero(among[k])
            if self.kernel == "compiled":
                out.append(point_kernels.row_median_residuals(self.D[k], np.ascontiguousarray(Y[:, 0]),
                                                        np.ascontiguousarray(Y[:, 1]), cols))
                continue
            from scipy.spatial.distance import cdist

            step = max(1, _BLOCK_ENTRIES // max(len(cols), 1))
            out.append(np.concatenate([
                np.median(np.abs(self.D[k][a:a + step, cols] - cdist(Y[a:a + step], Y[cols])), axis=1)
                for a in range(0, len(ids), step)]))
        return out

    @property
    def sparse(self) -> bool:
        """Whether some view is scored on a sparse pair set rather than all pairs."""
        return any(p is not None for p in self.pairs)

    def target_energy(self) -> float:
        """sum of D_ij^2 over the pairs the stress counts: its scale."""
        return sum(float(p[2] @ p[2]) if p else 0.5 * float(np.sum(D * D))
                   for D, p in zip(self.D, self.pairs))

    def _sparse_view(self, k: int, Y: np.ndarray, mask: np.ndarray | None, want_grad: bool):
        i, j, d = self.pairs[k]
        diff = Y[i] - Y[j]
        e = np.sqrt(np.einsum("pd,pd->p", diff, diff))
        r = d - e
        if mask is not None:
            r = r * mask
        w = None if self.alpha[k] is None else self.alpha[k][i] * self.alpha[k][j]
        total, r = _weighted_loss(r, w, self.loss, self.scale)
        if not want_grad:
            return total, None
        B = r / np.maximum(e, 1e-12)
        force = -2.0 * B[:, None] * diff  # dS/dy_i for each pair; dS/dy_j is its negative
        n = len(Y)
        grad = np.column_stack([np.bincount(i, force[:, c], n) - np.bincount(j, force[:, c], n)
                                for c in range(Y.shape[1])])
        return total, grad

    def _view(self, k: int, Y: np.ndarray, mask: np.ndarray | None, want_grad: bool):
        """Stress of view k and, if asked, dS/dY, for image points Y (n_k x 2)."""
        if self.kernel == "compiled":
            if self._kept[k] is not None and mask is None:
                keep, D, alpha = self._kept[k]
                total, g = kernels.view_stress(None, D, Y[keep], None, alpha, self._loss_code,
                                               self.scale, want_grad)
                if not want_grad:
                    return total, None
                grad = np.zeros_like(Y)
                grad[keep] = g
                return total, grad
            return kernels.view_stress(self.pairs[k], self.D[k], Y, mask, self.alpha[k],
                                       self._loss_code, self.scale, want_grad)
        if self.pairs[k] is not None:
            return self._sparse_view(k, Y, mask, want_grad)
        D = self.D[k]
        n = len(Y)
        grad = np.zeros_like(Y) if want_grad else None
        total = 0.0
        from scipy.spatial.distance import cdist  # the numpy reference only: scipy.spatial costs 0.14 s

        step = max(1, _BLOCK_ENTRIES // max(n, 1))
        for a in range(0, n, step):
            b = min(n, a + step)
            e = cdist(Y[a:b], Y)  # direct differences: exact to rounding, no Gram cancellation
            r = np.subtract(D[a:b], e)
            if mask is not None:
                r *= mask[a:b]
            w = None if self.alpha[k] is None else np.outer(self.alpha[k][a:b], self.alpha[k])
            value, r = _weighted_loss(r, w, self.loss, self.scale)
            total += value
            if want_grad:
                # The floor keeps 1/e finite on the diagonal and for coincident
                # images, where r is 0 or the pair's B_ij terms cancel below.
                np.maximum(e, 1e-12, out=e)
                r /= e  # now B
                grad[a:b] = 2.0 * (r @ Y - r.sum(axis=1)[:, None] * Y[a:b])
        # Each pair i > j appears twice in the full matrix.
        return 0.5 * total, grad

    def value(self, X: np.ndarray, P: np.ndarray, masks=None) -> float:
        """S(X, P), Eq. 1 (each pair i > j once)."""
        if masks is None and self._pack():
            return self._all_views(X, P, False, False)[0]
        return sum(self._view(k, X[ids] @ P[k].T, None if masks is None else masks[k], False)[0]
                   for k, ids in enumerate(self.ids))

    def view_rms(self, X: np.ndarray, P: np.ndarray) -> list[float]:
        """Per view, the RMS residual D_ij - ||P(x_i - x_j)|| over the pairs it counts."""
        out = []
        for k, ids in enumerate(self.ids):
            total = self._view(k, X[ids] @ P[k].T, None, False)[0]
            pairs = len(self.pairs[k][0]) if self.pairs[k] else len(ids) * (len(ids) - 1) // 2
            out.append(float(np.sqrt(total / max(pairs, 1))))
        return out

    def value_and_grad(self, X: np.ndarray, P: np.ndarray, masks=None, want_P: bool = False):
        """(S, dS/dX, dS/dP or None) at (X, P), optionally on a minibatch ``masks``."""
        if masks is None and self._pack():  # the loop below in one compiled call, the same bits
            return self._all_views(X, P, True, want_P)
        total = 0.0
        gX = np.zeros_like(X)
        gP = np.zeros_like(P) if want_P else None
        for k, ids in enumerate(self.ids):
            Xk = X[ids]
            s, gY = self._view(k, Xk @ P[k].T, None if masks is None else masks[k], True)
            total += s
            gX[ids] += gY @ P[k]  # ids are unique within a view
            if want_P:
                gP[k] = gY.T @ Xk
        return total, gX, gP

    def residual_spread(self, X: np.ndarray, P: np.ndarray, rng: np.random.Generator,
                        sample: int = 200_000) -> float:
        """1.4826 x the median absolute residual D - ||P(x_i - x_j)|| over a random
        sample of observed pairs: a robust estimate of the residuals' sigma."""
        residuals = []
        for k, ids in enumerate(self.ids):
            image = X[ids] @ P[k].T
            if self.pairs[k] is not None:
                i, j, d = self.pairs[k]
                pick = rng.integers(0, len(d), size=min(len(d), max(1, sample // len(self.ids))))
                residuals.append(d[pick] - np.linalg.norm(image[i[pick]] - image[j[pick]], axis=1))
                continue
            n = len(ids)
            i, j = rng.integers(0, n, size=(2, max(1, sample // len(self.ids))))
            keep = i != j
            i, j = i[keep], j[keep]
            residuals.append(self.D[k][i, j] - np.linalg.norm(image[i] - image[j], axis=1))
        return 1.4826 * float(np.median(np.abs(np.concatenate(residuals))))

    def sample_masks(self, c: float, rng: np.random.Generator):
        """A minibatch xi ~ Xi(D, c): each observed pair kept with probability c."""
        masks = []
        for ids, pairs in zip(self.ids, self.pairs):
            if pairs is not None:
                masks.append(rng.random(len(pairs[0])) < c)
                continue
            n = len(ids)
            keep = np.triu(rng.random((n, n), dtype=np.float32) < c, 1)
            masks.append(keep | keep.T)
        return masks


def project_rows(P: np.ndarray) -> np.ndarray:
    """Nearest matrices with orthonormal rows (polar factor), for each P^k."""
    U, _, Vt = np.linalg.svd(P, full_matrices=False)
    return U @ Vt
