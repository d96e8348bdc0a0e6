"""``refine``: the paper's stress (Eq. 1), minimised with full batches from ``factorize``.

L-BFGS over the points and, in the variable setting, the projections. A
projection stays exactly orthonormal by construction: P^k is the first two
rows of C(W_k) R0_k, with R0_k the starting rotation and C the Cayley map of
a skew-symmetric W_k, whose three entries are the variables. An optional
robust loss (``huber`` or ``soft_l1``, with a scale from the MAD of the
starting residuals) tempers corrupted distance rows and wrong
correspondences.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize


from .base import Choice, Interval, Observations, Reconstruction, register
from .factorize import solve_factorize
from .stress import LOSSES, Stress

# Huber's tuning constant: 95% efficiency under Gaussian residuals.
_HUBER_K = 1.345
# Stress / sum of squared distances below which the start is exact: RMS relative
# residuals of 1e-9, the precision of the per-view Lanczos MDS.
_EXACT = 1e-18
# Above this relative stress after descent the views are noisy, and refine also
# descends from the paper's smart (MDS) start, keeping the lower objective.
_NOISY = 1e-10


def _skew(w: np.ndarray) -> np.ndarray:
    """(K, 3) -> (K, 3, 3) skew-symmetric matrices."""
    W = np.zeros((len(w), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    return W - W.transpose(0, 2, 1)


def _rotations(P: np.ndarray) -> np.ndarray:
    """Complete each P^k (orthonormal rows) into a rotation."""
    return np.concatenate([P, np.cross(P[:, 0], P[:, 1])[:, None, :]], axis=1)


def cayley(w: np.ndarray, R0: np.ndarray):
    """Rotations C(W) R0, and what the gradient through them needs."""
    I = np.eye(3)
    W = _skew(w)
    inv = np.linalg.inv(I - W)
    C = inv @ (I + W)
    return C @ R0, inv, C


def cayley_grad(G: np.ndarray, R0: np.ndarray, inv: np.ndarray, C: np.ndarray) -> np.ndarray:
    """dS/dw from dS/dR = G: with dC = (I - W)^-1 dW (I + C),
    dS = <(I - W)^-T G R0^T (I + C)^T, dW>, read off the skew entries."""
    M = inv.transpose(0, 2, 1) @ G @ R0.transpose(0, 2, 1) @ (np.eye(3) + C).transpose(0, 2, 1)
    return np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1)


def _objective(stress: Stress, shape, R0, fixed_P):
    """f(theta) and its gradient, theta = [X, w] (w only when P varies)."""
    N = shape[0]

    def unpack(theta):
        X = theta[:3 * N].reshape(N, 3)
        if fixed_P is not None:
            return X, fixed_P, None
        R, inv, C = cayley(theta[3 * N:].reshape(-1, 3), R0)
        return X, R[:, :2], (inv, C)

    def f(theta):
        X, P, cay = unpack(theta)
        value, gX, gP = stress.value_and_grad(X, P, want_P=cay is not None)
        if cay is None:
            return value, gX.ravel()
        G = np.concatenate([gP, np.zeros((len(gP), 1, 3))], axis=1)
        return value, np.concatenate([gX.ravel(), cayley_grad(G, R0, *cay).ravel()])

    return f, unpack


_PARAMETER_CONSTRAINTS = {
    "loss": Choice(LOSSES),
    "max_iter": Interval(int, 0, None),
    "tol": Interval(float, 0.0, None),
}


@register("refine", constraints=_PARAMETER_CONSTRAINTS, paper=False,
          summary="ours: factorize, then full-batch L-BFGS on the stress (robust losses optional)")
def solve_refine(observations: Observations, *, random_state=None,
                 loss: str = "l2", max_iter: int = 500, tol: float = 1e-12) -> Reconstruction:
    """Full-batch L-BFGS on the 3DMPE stress, started from ``factorize``.

    Parameters
    ----------
    loss : {"l2", "huber", "soft_l1"}, default "l2"
        ``l2`` is the paper's stress. The robust losses are quadratic up to a
        scale of 1.345 x 1.4826 x MAD of the starting residuals and linear
        beyond it.
    max_iter : int, default 500
        L-BFGS iterations.
    tol : float, default 1e-12
        Relative decrease of the objective below which L-BFGS stops.

    There is no ``init``: the start is ``factorize``'s exact algebraic
    solution. When the descent from it ends at a relative stress above 1e-10
    (noisy views, where the algebraic start can land in a poor basin), refine
    also descends from the paper's smart start and keeps the lower objective.
    The result is never worse than the start: if the minimiser ends higher,
    the start is returned.
    """
    rng = np.random.default_rng(random_state)
    start = solve_factorize(observations, random_state=rng)
    X0, P0 = start.points, start.projections
    scale = 1.0
    if loss != "l2":
        spread = Stress(observations).residual_spread(X0, P0, rng)
        radius = float(np.sqrt(np.mean((X0 - X0.mean(axis=0)) ** 2))) or 1.0
        scale = max(_HUBER_K * spread, 1e-12 * radius)  # noise-free: residuals are ~0
    stress = Stress(observations, loss, scale)
    f0 = start.stress if loss == "l2" else None  # the start's stress is known
    total = stress.target_energy()
    X, P, value, history, iterations, termination = _descend(observations, stress, X0, P0, f0,
                                                             max_iter, tol, total)
    used_start = "factorize"
    if value > _NOISY * total and not stress.sparse:  # noisy views: the algebraic start
        # may sit in a poor basin; the smart start is an N x N MDS, so only when dense
        from .sgd import initial_state

        Xs, Ps = initial_state(observations, Stress(observations), "smart", rng, "smacof")
        alt = _descend(observations, stress, Xs, Ps, None, max_iter, tol, total)
        if alt[2] < value:
            X, P, value, history, iterations, termination = alt
            used_start = "smart (MDS)"
    exact = iterations == 0 and used_start == "factorize" and value == f0
    if exact and loss == "l2":
        paper_stress = start.stress
    else:
        paper_stress = value if loss == "l2" else Stress(observations).value(X, P)
    return Reconstruction(points=X, projections=P, stress=paper_stress,
                          stress_history=np.array(history), iterations=iterations,
                          termination=termination,
                          info={"unplaced": start.info["unplaced"], "loss": loss,
                                "loss_scale": scale, "objective": value, "start": used_start,
                                "start_stress": start.stress})


def _descend(observations: Observations, stress: Stress, X0: np.ndarray, P0: np.ndarray,
             f0: float | None, max_iter: int, tol: float, total: float):
    """L-BFGS from (X0, P0): the points, projections, objective, history, iterations, reason."""
    R0 = _rotations(P0)
    f, unpack = _objective(stress, X0.shape, R0, P0 if observations.fixed else None)
    theta0 = X0.ravel() if observations.fixed else np.concatenate([X0.ravel(), np.zeros(3 * len(P0))])
    f0 = f(theta0)[0] if f0 is None else f0
    history = [f0]
    if f0 <= _EXACT * total:  # residuals at rounding level
        theta, value, iterations = theta0, f0, 0
        termination = "start already exact (relative stress below 1e-18)"
    else:
        theta, value, iterations, termination = _minimise(f, theta0, history, max_iter, tol)
    X, P, _ = unpack(theta)
    return X, np.array(P), value, history, iterations, termination
def _minimise(f, theta0: np.ndarray, history: list, max_iter: int, tol: float):
    """L-BFGS-B from theta0; the start back if it somehow ends higher."""
    def record(intermediate_result):  # scipy passes the OptimizeResult by this name
        history.append(float(intermediate_result.fun))

    result = minimize(f, theta0, jac=True, method="L-BFGS-B", callback=record,
                      options={"maxiter": max_iter, "ftol": tol, "gtol": 0.0, "maxcor": 20})
    termination = str(result.message)
    if result.status == 2:  # L-BFGS-B's "ABNORMAL": its line search found no decrease
        termination = "no further decrease at numerical precision"
    if result.fun > history[0]:  # the line search should prevent this; never trust it
        del history[1:]  # the start is kept: no iteration changed it
        return theta0, history[0], 0, "kept the factorize start (no decrease)"
    # scipy reports every accepted step to ``record``; one value per iteration.
    return result.x, float(result.fun), len(history) - 1, termination
