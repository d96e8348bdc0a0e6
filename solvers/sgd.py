"""The paper's solver: minibatch SGD on the 3DMPE stress (Algorithms 1 and 2).

Fixed setting (Algorithm 1): only X moves. Variable setting (Algorithm 2): X
and the projections P^k move together, each with its own adaptive step, and
each P^k is projected back to orthonormal rows after every step.

Choices the paper leaves open, and what we do:

* Minibatch: every observed pair is kept with probability ``c``. The authors'
  code in effect runs full batches (c = 1), and its small minibatches
  converged badly, so ``c = 1`` is the default.
* Step: Malitsky & Mishchenko (2020), "Adaptive gradient descent without
  descent", Algorithm 1: mu_t = min(sqrt(1 + theta_{t-1}) mu_{t-1},
  ||dX|| / (2 ||dG||)), theta_t = mu_t / mu_{t-1}, with both gradients taken
  on the same minibatch xi_t as the paper writes. The authors' code also keeps
  every step at least 3/4 of the previous one, which the published rule does
  not, and which lets runs diverge; we do not. ``step="bb"`` uses instead the
  formula printed in the paper, <dX, dG> / ||dG||^2 (a Barzilai-Borwein step),
  keeping the previous step where the curvature it measures is not positive.
* Stop: when the stress or the gradient norm falls below ``tol`` (1e-4 in the
  paper), or after ``max_iter`` iterations (300). The best iterate (lowest
  full-batch stress) is returned, so the result is never worse than the start.
* Smart start: the baseline embedding (MDS of the averaged distances), scaled
  by the closed-form factor that minimises its stress (projected distances
  shrink the average, so the raw MDS is too small). In the variable setting
  each P^k starts at its Procrustes fit to the embedding; in the fixed setting
  the embedding is first rotated into the frame of the given projections
  (:func:`align_to_projections`), since MDS returns an arbitrary orientation.
* Random start: points uniform in the unit cube (paper), random orthonormal
  projections in the variable setting.
"""

from __future__ import annotations

import numpy as np

from mpe3d.solvers.base import Choice, Interval, Observations, Reconstruction, register_solver
from mpe3d.solvers.starts import fit_projections, mds_embedding
from mpe3d.solvers.stress import Stress, project_rows


def random_projections(K: int, rng: np.random.Generator) -> np.ndarray:
    """K random 2x3 matrices with orthonormal rows (rows of Haar rotations)."""
    Q, R = np.linalg.qr(rng.standard_normal((K, 3, 3)))
    Q *= np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]
    return Q[:, :2, :]


def align_to_projections(P_fit: np.ndarray, P: np.ndarray, rng: np.random.Generator,
                         restarts: int = 32, sweeps: int = 500) -> np.ndarray:
    """The O(3) matrix Q that best explains P_fit[k] = R_k P[k] Q, with R_k in O(2).

    ``P_fit`` are projections fitted to an embedding in an arbitrary frame;
    ``P`` are the true ones. Alternates 2D and 3D orthogonal Procrustes (until
    the fit stops improving) from random starts and keeps the best fit: the
    alternation has several local optima (we saw 6 distinct ones on a chair),
    and the fit's error ranks them as the stress of the resulting start does.
    """
    starts = np.empty((restarts, 3, 3))
    starts[:1] = np.eye(3)
    starts[1:] = project_rows(rng.standard_normal((restarts - 1, 3, 3)))
    Q, err = procrustes_restarts(P_fit, P, starts, sweeps)
    best, best_err = np.eye(3), np.inf
    for start in range(restarts):  # the first of equal fits, and never a NaN one
        if err[start] < best_err:
            best, best_err = Q[start], err[start]
    return best


def procrustes_restarts(P_fit: np.ndarray, P: np.ndarray, starts: np.ndarray,
                        sweeps: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """Each start's alternation of :func:`align_to_projections`: its last Q and error.

    All starts advance together, one batch of small SVDs a sweep, and a start
    leaves the batch when its fit stops improving by 1e-15. Python's overhead
    a sweep, not LAPACK, was most of the time one start at a time (16,000
    sweeps of 2 SVDs on a torus: 1 s of a 1.1 s run). Every start's arithmetic
    is the one it had alone, so the results are the same bits."""
    Q = starts.copy()
    err = np.full(len(starts), np.inf)
    active = np.arange(len(starts))
    for _ in range(sweeps):
        if active.size == 0:
            break
        R = project_rows(P_fit @ np.swapaxes(P @ Q[active, None], 2, 3))  # (n, K, 2, 2)
        Q_new = project_rows(np.einsum("kai,nkab,kbj->nij", P, np.swapaxes(R, 2, 3), P_fit))
        err_new = np.sum((P_fit - R @ P @ Q_new[:, None]) ** 2, axis=(1, 2, 3))
        stalled = err[active] - err_new < 1e-15  # False for NaN, as it was one start at a time
        Q[active], err[active] = Q_new, err_new
        active = active[~stalled]
    return Q, err


def _best_scale(stress: Stress, X: np.ndarray, P: np.ndarray) -> float:
    """argmin_s S(sX, P) in closed form: s = sum D e / sum e^2 (rows sampled past 2048)."""
    from scipy.spatial.distance import cdist  # here: importing scipy.spatial costs 0.18 s a process

    num = den = 0.0
    for k, ids in enumerate(stress.ids):
        Y = X[ids] @ P[k].T
        rows = np.linspace(0, len(ids) - 1, min(len(ids), 2048)).astype(int)
        e = cdist(Y[rows], Y)
        num += float(np.sum(stress.D[k][rows] * e))
        den += float(np.sum(e * e))
    return num / den if den > 0 else 1.0


def initial_state(obs: Observations, stress: Stress, init: str, rng: np.random.Generator,
                  baseline_method: str):
    """(X0, P0) for ``init`` = smart or random."""
    if init == "random":
        X = rng.uniform(0.0, 1.0, size=(obs.n_points, 3))
        P = obs.projections if obs.fixed else random_projections(obs.n_views, rng)
        return X, P
    X = mds_embedding(obs, baseline_method, random_state=rng)
    P_fit = fit_projections(X, obs, rng)
    if obs.fixed:
        Q = align_to_projections(P_fit, obs.projections, rng)
        X, P = X @ Q.T, obs.projections
    else:
        P = P_fit
    return X * _best_scale(stress, X, P), P


class _Step:
    """One adaptive step size, updated from successive iterates and gradients."""

    def __init__(self, rule: str, mu0: float):
        self.rule, self.mu, self.theta = rule, mu0, np.inf

    def update(self, dx: np.ndarray, dg: np.ndarray) -> float:
        ndg = float(np.linalg.norm(dg))
        if ndg == 0.0 or not np.isfinite(ndg):
            return self.mu
        if self.rule == "mm":
            mu = min(np.sqrt(1.0 + self.theta) * self.mu, float(np.linalg.norm(dx)) / (2.0 * ndg))
            if not np.isfinite(mu) or mu <= 0.0:  # no move, or a vanishing gradient change
                return self.mu
            self.theta, self.mu = mu / self.mu, mu
        else:
            curvature = float(np.vdot(dx, dg))
            if curvature > 0:
                self.mu = curvature / ndg ** 2
        return self.mu


def _first_step(X: np.ndarray, g: np.ndarray) -> float:
    """A small first step: moves the cloud by 1e-4 of its size."""
    ng = float(np.linalg.norm(g))
    return 1e-4 * float(np.linalg.norm(X - X.mean(axis=0))) / ng if ng > 0 else 1e-6


_PARAMETER_CONSTRAINTS = {
    "c": Interval(float, 0.0, 1.0, closed="right"),
    "max_iter": Interval(int, 0, None),
    "tol": Interval(float, 0.0, None),
    "step": Choice(("mm", "bb")),
    "baseline_method": Choice(("smacof", "classical")),
}


@register_solver("sgd", constraints=_PARAMETER_CONSTRAINTS, paper=True,
          summary="the paper's 3DMPE: minibatch SGD with an adaptive step from the smart start")
def solve_sgd(observations: Observations, *, init: str = "smart", random_state=None,
              c: float = 1.0, max_iter: int = 300, tol: float = 1e-4, step: str = "mm",
              baseline_method: str = "smacof") -> Reconstruction:
    """Minimise the 3DMPE stress (Eq. 1) by minibatch SGD with an adaptive step.

    Parameters
    ----------
    c : float, default 1.0
        Probability that an observed pair is in a minibatch (the paper's
        stochastic constant); 1 means full batches.
    max_iter : int, default 300
        Iteration limit (the paper's T).
    tol : float, default 1e-4
        Stop when the stress or the gradient norm falls below it.
    step : {"mm", "bb"}, default "mm"
        Malitsky-Mishchenko (2020) adaptive step, or the paper's printed
        Barzilai-Borwein formula.
    baseline_method : {"smacof", "classical"}, default "smacof"
        The MDS behind the smart start.
    """
    rng = np.random.default_rng(random_state)
    stress = Stress(observations)
    fixed = observations.fixed
    X, P = initial_state(observations, stress, init, rng, baseline_method)

    def batch():
        return None if c >= 1.0 else stress.sample_masks(c, rng)

    def evaluate(X, P, masks):
        return stress.value_and_grad(X, P, masks, want_P=not fixed)

    full = stress.value(X, P)
    history = [full]
    best = (full, X, P)
    masks = batch()
    _, gX, gP = evaluate(X, P, masks)
    step_X = _Step(step, _first_step(X, gX))
    step_P = None if fixed else _Step(step, _first_step(P, gP))
    termination = "max_iter reached"
    while len(history) <= max_iter:
        grad_norm = np.sqrt(np.sum(gX ** 2) + (0.0 if fixed else np.sum(gP ** 2)))
        if full < tol or grad_norm < tol:
            termination = "stress below tol" if full < tol else "gradient below tol"
            break
        X_new = X - step_X.mu * gX
        P_step = P if fixed else P - step_P.mu * gP
        if not (np.all(np.isfinite(X_new)) and np.all(np.isfinite(P_step))):
            termination = "non-finite step"  # the adaptive step overflowed on a flat stress
            break
        P_new = P if fixed else project_rows(P_step)
        s_new, gX_new, gP_new = evaluate(X_new, P_new, masks)
        if not np.isfinite(s_new):
            termination = "non-finite stress"
            break
        # Both gradients of a step come from the same minibatch xi_t (Algorithm 1).
        step_X.update(X_new - X, gX_new - gX)
        if not fixed:
            step_P.update(P_new - P, gP_new - gP)
        X, P = X_new, P_new
        full = s_new if masks is None else stress.value(X, P)
        history.append(full)
        if full < best[0]:
            best = (full, X, P)
        if masks is None:
            gX, gP = gX_new, gP_new
        else:
            masks = batch()
            _, gX, gP = evaluate(X, P, masks)
    full, X, P = best
    return Reconstruction(points=X, projections=P, stress=full,
                          stress_history=np.asarray(history), iterations=len(history) - 1,
                          termination=termination, info={"step_X": step_X.mu})
