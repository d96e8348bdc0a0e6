"""One contract for every registered solver, as scikit-learn's ``parametrize_with_checks``
holds every estimator to one: what a result is, and what its fields mean."""
import numpy as np
import pytest

from mpe3d import solvers
from mpe3d.errors import MpeError
from mpe3d.solvers.base import Choice, Interval
from mpe3d.solvers.stress import Stress
from tests.helpers import scene_and_observations

NAMES = sorted(solvers.SOLVERS)
QUICK = {"sgd": {"max_iter": 60}}  # the contract, not the accuracy, is under test


@pytest.fixture(scope="module", params=["fixed", "variable"])
def observations(request):
    _, _, obs = scene_and_observations(points=64, views=4, projections=request.param)
    return obs


@pytest.mark.parametrize("name", NAMES)
def test_every_solver_keeps_the_contract(name, observations):
    first = solvers.solve(name, observations, random_state=3, **QUICK.get(name, {}))
    X, P = first.points, first.projections
    assert X.shape == (observations.n_points, 3) and np.all(np.isfinite(X))
    assert P.shape == (observations.n_views, 2, 3)
    assert np.allclose(P @ np.swapaxes(P, 1, 2), np.eye(2), atol=1e-10)
    if observations.fixed:
        assert np.array_equal(P, observations.projections)
    # One meaning for the history and the iteration count, whatever the method.
    history = np.asarray(first.stress_history)
    assert history.ndim == 1 and len(history) >= 1 and np.all(np.isfinite(history))
    assert first.iterations == len(history) - 1
    assert first.stress == pytest.approx(Stress(observations).value(X, P), rel=1e-9, abs=1e-12)
    assert first.runtime_s > 0 and first.termination
    # The same seed gives the same result, to the last bit.
    again = solvers.solve(name, observations, random_state=3, **QUICK.get(name, {}))
    assert np.array_equal(again.points, X) and np.array_equal(again.projections, P)
    assert np.array_equal(again.stress_history, history)


def _outside(rule):
    if isinstance(rule, Choice):
        return "no-such-choice"
    if rule.low is not None:
        return rule.kind(rule.low) - (1 if rule.closed in ("both", "left") else 0)
    return rule.kind(rule.high) + 1


@pytest.mark.parametrize("name", NAMES)
def test_every_option_has_a_rule_that_is_enforced(name):
    spec = solvers.SOLVERS[name]
    assert spec.summary and isinstance(spec.paper, bool)
    options = spec.options()
    assert set(options) == set(spec.constraints)
    for option, rule in spec.constraints.items():
        assert isinstance(rule, (Interval, Choice))
        assert options[option] in rule, f"{name}: the default of {option} breaks its own rule"
        with pytest.raises(MpeError, match=rf"solver\.{option}: expected .* for solver '{name}'"):
            solvers.validate_options(name, {option: _outside(rule)})
    if "max_iter" in options:
        with pytest.raises(MpeError, match="expected an integer"):
            solvers.validate_options(name, {"max_iter": 2.5})


def test_init_goes_only_to_solvers_that_take_it(observations):
    takers = {name for name, spec in solvers.SOLVERS.items() if spec.uses_init}
    assert takers == {"sgd"}
    # A solver without a start accepts any init, as documented; sgd checks it.
    solvers.solve("factorize", observations, init="random", random_state=0)
    with pytest.raises(MpeError, match="init: '.*' is not one of smart, random"):
        solvers.solve("sgd", observations, init="zeros", random_state=0)
