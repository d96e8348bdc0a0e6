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

from mpe3d.options import STRESS_LOSSES
from mpe3d.solvers import lbfgs, point_kernels
from mpe3d.solvers.base import Choice, Interval, Observations, Reconstruction, register_solver
from mpe3d.solvers.factorize import solve_factorize
from mpe3d.solvers.stress import Stress

# Huber's tuning constant: 95% efficiency under Gaussian residuals.
_HUBER_K = 1.345
# Stress / sum of squared distances below which the start is exact: RMS relative
# residuals of 1e-9, the precision of the per-view Lanczos MDS.
_EXACT_STRESS = 1e-18
# Above this relative stress after descent the views are noisy, and refine also
# descends from the paper's smart (MDS) start, keeping the lower objective.
_NOISY = 1e-10
# An observation whose row misfits beyond the rows' median by this many robust
# sigmas of theirs is rejected: a corrupted distance row, or a wrong match.
ROW_SIGMAS = 5.0
_REJECTION_ROUNDS = 6
# Noisy views: a descent stops at this relative decrease while the objective is
# above _NOISY, because digits below the noise are not worth their iterations
# (50 runs of the paper's noise sweeps: 30 % of refine's time; Chamfer distances
# within 1 % but for a few runs, either way). No descent on the clean views of
# the paper's sweeps decreases this slowly above _NOISY: theirs are unchanged.
NOISY_TOL = 1e-9
_PLACING_STEPS = 10  # Gauss-Newton steps placing one point from its distance rows
_REWEIGHTS = 3  # rounds of reweighting a weak point's rows by their misfits
# Anchors per row while scouting a weak point's view pairs (the last fit uses all):
# the median misfit of 64 distances already tells a clean row from a corrupted one.
_SCOUTS = 64
# The rounds end when fewer observations than this share change side.
_SETTLED = 1e-3
OUTLIERS = ("reject", "keep")


def _skew(w: np.ndarray) -> np.ndarray:
    """(K, 3) -> (K, 3, 3) skew-symmetric matrices."""
    W = np.zeros((len(w), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    return W - W.transpose(0, 2, 1)


def rotations_of(P: np.ndarray) -> np.ndarray:
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


def stress_objective(stress: Stress, shape, R0, fixed_P, unit: float = 1.0):
    """f(theta) and its gradient, theta = [X, w * unit] (w only when P varies; ``unit``
    from :func:`rotation_unit`)."""
    N = shape[0]

    def unpack(theta):
        X = theta[:3 * N].reshape(N, 3)
        if fixed_P is not None:
            return X, fixed_P, None
        R, inv, C = cayley(theta[3 * N:].reshape(-1, 3) / unit, R0)
        return X, R[:, :2], (inv, C)

    def f(theta):
        X, P, cay = unpack(theta)
        value, gX, gP = stress.value_and_grad(X, P, want_P=cay is not None)
        if cay is None:
            return value, gX.ravel()
        G = np.concatenate([gP, np.zeros((len(gP), 1, 3))], axis=1)
        return value, np.concatenate([gX.ravel(), cayley_grad(G, R0, *cay).ravel() / unit])

    return f, unpack


def rotation_unit(X: np.ndarray) -> float:
    """The length a unit of the rotation variables stands for: the cloud's RMS
    radius when it exceeds 1, else 1.

    L-BFGS starts from the identity, as if a radian of rotation and a unit of
    length were alike. A rotation moves the points by about the radius per
    radian, so its curvature grows with radius^2: on COLMAP's tracks in pixels
    (250 views, radius ~1e4) the descent crawled at steps of 1e-15, 7
    evaluations an iteration, and ended 3x above where it ends with the
    rotations measured in radii. On clouds of radius 1 or less (the paper's
    shapes, scaled to a unit diagonal) the plain variables stay: measuring
    rotations in their radius (~0.35) doubled refine's time on the noise
    sweeps."""
    radius = float(np.sqrt(np.mean(np.sum((X - X.mean(axis=0)) ** 2, axis=1))))
    return radius if radius > 1.0 else 1.0


_PARAMETER_CONSTRAINTS = {
    "loss": STRESS_LOSSES,
    "max_iter": Interval(int, 0, None),
    "tol": Interval(float, 0.0, None),
    "outliers": Choice(OUTLIERS),
}


@register_solver("refine", constraints=_PARAMETER_CONSTRAINTS, paper=False, exact=True,
          summary="ours: factorize, then full-batch L-BFGS on the stress (robust losses optional)")
def solve_refine(observations: Observations, *, random_state=None,
                 loss: str = "l2", max_iter: int = 500, tol: float = 1e-12,
                 outliers: str = "reject") -> Reconstruction:
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
        Relative decrease of the objective below which L-BFGS stops; on
        noisy views, while the relative stress is above 1e-10, at
        max(tol, NOISY_TOL = 1e-9).
    outliers : {"reject", "keep"}, default "reject"
        ``reject``: when the views are noisy, each observation (view k, point
        i) whose distance row misfits (median |residual| over the row) beyond
        the rows' median by ROW_SIGMAS robust sigmas is taken for corrupted,
        its alpha_i^k in Eq. 1 set to REJECTED_ALPHA, and the stress solved
        again, until the rejected set stops changing. A corrupted row or a
        wrong match in one view then no longer bends the cloud. ``keep``
        minimises the paper's stress as it stands.

    There is no ``init``: the start is ``factorize``'s exact algebraic
    solution. When the descent from it ends at a relative stress above 1e-10
    (noisy views, where the algebraic start can land in a poor basin), refine
    also descends from the paper's smart start and keeps the lower objective.
    When factorize says its cloud of noisy dense views is undetermined along
    a direction (``info["degenerate"]``), refine descends from the smart start
    alone.
    With ``outliers="keep"`` the result is never worse than the start: if the
    minimiser ends higher, the start is returned. Rejecting observations
    trades the paper's stress for a fit that the corrupted rows do not bend,
    so its Eq. 1 may end above the start's; ``info["rejected"]`` counts them.
    """
    rng = np.random.default_rng(random_state)
    start = solve_factorize(observations, random_state=rng)
    X0, P0 = start.points, start.projections
    scale = 1.0
    radius = float(np.sqrt(np.mean((X0 - X0.mean(axis=0)) ** 2))) or 1.0
    # An exact start has every residual at rounding level, deep inside any robust
    # loss's quadratic zone: its robust objective is its stress, and it is kept.
    plain = Stress(observations)  # Eq. 1 itself, whatever the loss
    total = plain.target_energy()
    exact_start = start.stress <= _EXACT_STRESS * total
    if loss != "l2":
        spread = 0.0 if exact_start else plain.residual_spread(X0, P0, rng)
        scale = max(_HUBER_K * spread, 1e-12 * radius)  # noise-free: residuals are ~0
    stress = Stress(observations, loss, scale)
    f0 = start.stress if loss == "l2" or exact_start else None  # the start's stress is known
    # factorize's noisy cloud left undetermined along a direction (it said so): L-BFGS
    # from it crawls (gradients of 1e9, steps of 1e-14) to a basin the MDS start beats
    hopeless = start.info["degenerate"] and start.stress > _NOISY * total and not stress.sparse
    used_start = "factorize"
    if hopeless:  # kept only if the smart start's descent ends higher still
        value = stress.value(X0, P0) if f0 is None else f0
        X, P, history, iterations = X0, P0, [value], 0
        termination = "factorize's start, undetermined along a direction"
    else:
        X, P, value, history, iterations, termination = _descend(
            observations, stress, X0, P0, f0, max_iter, _noisy_tol(tol, total), total)
    if value > _NOISY * total and not stress.sparse:  # noisy views: the algebraic start
        # may sit in a poor basin; the smart start is an N x N MDS, so only when dense
        from mpe3d.solvers.sgd import initial_state

        Xs, Ps = initial_state(observations, plain, "smart", rng, "smacof")
        alt = _descend(observations, stress, Xs, Ps, None, max_iter, _noisy_tol(tol, total), total)
        if alt[2] < value:
            X, P, value, history, iterations, termination = alt
            used_start = "smart (MDS)"
    rejected = 0
    if outliers == "reject" and value > _NOISY * total and not stress.sparse:
        X, P, value, history, iterations, reason, rejected = _rejecting(
            observations, stress, X, P, history, iterations, max_iter, max(tol, NOISY_TOL), total)
        termination = reason or termination
    exact = iterations == 0 and used_start == "factorize" and value == f0
    if exact and (loss == "l2" or exact_start):
        paper_stress = start.stress
    else:
        paper_stress = value if loss == "l2" and not rejected else plain.value(X, P)
    return Reconstruction(points=X, projections=P, stress=paper_stress,
                          stress_history=np.array(history), iterations=iterations,
                          termination=termination,
                          info={"unplaced": start.info["unplaced"], "loss": loss,
                                "loss_scale": scale, "objective": value, "start": used_start,
                                "start_stress": start.stress, "rejected": rejected})


def _rejecting(observations, stress, X, P, history, iterations, max_iter, tol, total):
    """Reject the observations whose rows misfit, solve again, repeat until the
    rejected set is stable: the result, and how many observations it rejects.

    Each round solves without the rejected observations (alpha 0), which fixes
    the projections and every point still kept in two views. The points that
    are not (weak: they have no depth without their rejected rows) are then
    placed one by one against the others, from the pair of their views that
    the rest of their views agree with best (:func:`_place_weak`): a row
    rejected only because the distorted first fit misplaced its point fits
    again there, and is taken back in the next round.
    """
    rejected = [np.zeros(len(ids), dtype=bool) for ids in stress.ids]
    value, termination = None, None
    for _ in range(_REJECTION_ROUNDS):
        now = _misfits(stress, X, P, rejected, total)
        changed = sum(int(np.sum(a != b)) for a, b in zip(now, rejected))
        if changed == 0 or (value is not None and changed <= _SETTLED * sum(map(len, now))):
            break
        rejected = now
        weak = _weak(stress, rejected)
        X, P, value, more, steps, termination = _descend(
            observations, stress.weighted([np.where(r, 0.0, 1.0) for r in rejected]), X, P, None,
            max_iter, tol, total)
        history, iterations = history + more[1:], iterations + steps
        if weak.any():
            X = _place_weak(stress, X, P, weak, rejected, total)
    value = stress.value(X, P) if value is None else value
    return X, P, value, history, iterations, termination, int(sum(r.sum() for r in rejected))


def _place_weak(stress, X, P, weak, rejected, total) -> np.ndarray:
    """Each weak point placed against the points kept: from the pair of its
    views with the lowest truncated misfit over all of its views (MSAC, the
    truncation at the rejection line), then from all of its views, each
    weighted by its inverse misfit variance (floored at the line's sigma), so
    that a clean row fixes the point in its view and the rows of corrupted
    distances, which still know its depth, add only that."""
    line = _line(stress, X, P, rejected, total)
    X = X.copy()
    anchors = _anchors(stress, X, P, ~weak, rejected)  # they do not move here: made once
    position = np.full((len(stress.ids), stress.n_points), -1)  # point -> its row in each view
    for k, ids in enumerate(stress.ids):
        position[k, ids] = np.arange(len(ids))
    for i in np.flatnonzero(weak):
        rows = [(Pk, Y, stress.D[k][position[k, i], cols]) for k, (cols, Pk, Y) in enumerate(anchors)
                if position[k, i] >= 0 and len(cols)]
        if len(rows) < 2:
            continue
        # one compiled call per point: the Python around the scouting of each pair
        # of its views was half of this function's time
        X[i] = point_kernels.place_point(np.asarray(X[i], dtype=np.float64), *_stack(rows), float(line),
                                   ROW_SIGMAS, _SCOUTS, _REWEIGHTS, _PLACING_STEPS)
    return X


def _anchors(stress, X, P, anchor, rejected):
    """Per view, the ``anchor`` points kept there: their columns in the view,
    P^k once per anchor, and their images."""
    out = []
    for k, ids in enumerate(stress.ids):
        cols = np.flatnonzero(anchor[ids] & ~rejected[k])
        out.append((cols, np.broadcast_to(P[k], (len(cols), 2, 3)), X[ids[cols]] @ P[k].T))
    return out


def _stack(rows):
    """Rows (P per anchor, images, distances) as one set of anchors for the
    kernels: (P, images, distances, each row's start)."""
    sizes = [len(d) for _, _, d in rows]
    return (np.ascontiguousarray(np.concatenate([Pk for Pk, _, _ in rows])),
            np.concatenate([Y for _, Y, _ in rows]), np.concatenate([d for _, _, d in rows]),
            np.concatenate([[0], np.cumsum(sizes)]))


def _weak(stress, rejected) -> np.ndarray:
    """The points kept in fewer than two views: their depth needs the rejected rows."""
    kept = np.zeros(stress.n_points, dtype=int)
    for r, ids in zip(rejected, stress.ids):
        kept[ids[~r]] += 1
    return kept < 2


def _misfits(stress, X, P, rejected, total):
    """Per view, the observations whose row misfits beyond the rows' median by
    ROW_SIGMAS robust sigmas (rows measured against the points not rejected)."""
    misfit = stress.row_residuals(X, P, [~r for r in rejected])
    line = _line(stress, X, P, rejected, total, misfit)
    return [m > line for m in misfit]


def _line(stress, X, P, rejected, total, misfit=None) -> float:
    """The rejection line: the rows' median misfit plus ROW_SIGMAS robust sigmas."""
    if misfit is None:
        misfit = stress.row_residuals(X, P, [~r for r in rejected])
    every = np.concatenate(misfit)
    middle = np.median(every)
    # floored: rounding-level residuals of a near-exact fit are no outliers
    sigma = max(1.4826 * np.median(np.abs(every - middle)), 1e-6 * np.sqrt(total / stress.n_pairs))
    return middle + ROW_SIGMAS * sigma


def _noisy_tol(tol: float, total: float):
    """L-BFGS's tolerance as a function of the objective: ``tol``, or
    NOISY_TOL while the relative stress is above _NOISY."""
    loose = max(tol, NOISY_TOL)
    return lambda value: loose if value > _NOISY * total else tol


def _descend(observations: Observations, stress: Stress, X0: np.ndarray, P0: np.ndarray,
             f0: float | None, max_iter: int, tol, total: float):
    """L-BFGS from (X0, P0): the points, projections, objective, history,
    iterations, reason. ``tol`` is a number or a function of the objective."""
    R0 = rotations_of(P0)
    f, unpack = stress_objective(stress, X0.shape, R0, P0 if observations.fixed else None,
                                 rotation_unit(X0))
    theta0 = X0.ravel() if observations.fixed else np.concatenate([X0.ravel(), np.zeros(3 * len(P0))])
    start = f(theta0) if f0 is None else None
    f0 = start[0] if f0 is None else f0
    history = [f0]
    if f0 <= _EXACT_STRESS * total:  # residuals at rounding level
        theta, value, iterations = theta0, f0, 0
        termination = "start already exact (relative stress below 1e-18)"
    else:
        result = lbfgs.minimize(f, theta0, max_iter=max_iter, ftol=tol, start=start,
                                callback=history.append)
        theta, value, iterations, termination = result.x, result.fun, result.nit, result.message
    X, P, _ = unpack(theta)
    return X, np.array(P), value, history, iterations, termination
