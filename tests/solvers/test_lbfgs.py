"""refine's L-BFGS: it must find the minima scipy's L-BFGS-B finds."""

import numpy as np
from scipy.optimize import minimize as scipy_minimize
from scipy.optimize import rosen, rosen_der

from mpe3d.solvers import lbfgs


def _rosenbrock(x):
    return rosen(x), rosen_der(x)


def test_rosenbrock_reaches_the_minimum():
    history = []
    result = lbfgs.minimize(_rosenbrock, np.full(10, -1.2), max_iter=500, ftol=1e-15,
                            callback=history.append)
    assert result.converged
    assert np.allclose(result.x, 1.0, atol=1e-6)
    assert result.nit == len(history)
    assert all(b <= a for a, b in zip(history, history[1:]))  # every step decreases f


def test_quadratic_as_scipy_finds_it(rng):
    A = rng.normal(size=(40, 40))
    H = A @ A.T + 0.1 * np.eye(40)
    b = rng.normal(size=40)

    def quadratic(x):
        return 0.5 * x @ H @ x - b @ x, H @ x - b

    ours = lbfgs.minimize(quadratic, np.zeros(40), max_iter=1000, ftol=1e-16)
    theirs = scipy_minimize(quadratic, np.zeros(40), jac=True, method="L-BFGS-B",
                            options={"maxiter": 1000, "ftol": 1e-16, "gtol": 0.0, "maxcor": 20})
    exact = np.linalg.solve(H, b)
    assert np.linalg.norm(ours.x - exact) <= 1e-6 * np.linalg.norm(exact)
    assert ours.fun <= theirs.fun + 1e-9 * abs(theirs.fun)


def test_a_wall_of_infinities_is_backed_off_from():
    """Beyond x = 0.5 the objective is inf (an overflowing stress): the line
    search must shrink its step instead of stopping or stepping there."""
    def walled(x):
        if x[0] > 0.5:
            return np.inf, np.full_like(x, np.nan)
        return float((x[0] - 0.4) ** 2 + x[1] ** 2), np.array([2 * (x[0] - 0.4), 2 * x[1]])

    result = lbfgs.minimize(walled, np.array([-3.0, 1.0]), max_iter=100, ftol=1e-15)
    assert np.allclose(result.x, [0.4, 0.0], atol=1e-6) and np.isfinite(result.fun)


def test_a_start_at_the_minimum_is_returned():
    def bowl(x):
        return float(x @ x), 2 * x

    result = lbfgs.minimize(bowl, np.zeros(3), max_iter=10, ftol=1e-12)
    assert result.nit == 0 and result.message == lbfgs.ZERO_GRADIENT
    assert np.array_equal(result.x, np.zeros(3))


def test_max_iter_is_a_hard_limit():
    result = lbfgs.minimize(_rosenbrock, np.full(6, -1.2), max_iter=3, ftol=0.0)
    assert result.nit == 3 and result.message == lbfgs.MAX_ITER and not result.converged


def test_a_tolerance_that_depends_on_the_objective_applies_where_it_is_reached():
    """refine's noisy-view rule: one tolerance above a level, another below.
    The steps are those of a constant tolerance until the stop, which comes
    at the first iteration whose reduction is below its objective's tolerance."""
    start = np.full(10, -1.2)
    history = []
    lbfgs.minimize(_rosenbrock, start, max_iter=500, ftol=1e-15, callback=history.append)
    f = np.array([_rosenbrock(start)[0], *history])
    reduction = (f[:-1] - f[1:]) / np.maximum(np.maximum(abs(f[:-1]), abs(f[1:])), 1.0)
    stops = []
    for above, below in ((1e-2, 1e-15), (1e-15, 1e-2)):  # loose above 1, then loose below it
        expected = 1 + int(np.flatnonzero(np.where(f[1:] > 1.0, reduction <= above,
                                                   reduction <= below))[0])
        result = lbfgs.minimize(_rosenbrock, start, max_iter=500,
                                ftol=lambda value, above=above, below=below:
                                above if value > 1.0 else below)
        assert result.nit == expected and result.converged
        assert result.fun == f[expected]  # the same path, stopped there
        stops.append(expected)
    assert stops[0] < stops[1] < len(history)  # each rule stopped somewhere else
