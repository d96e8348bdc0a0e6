"""Run one registered solver: its options and the observations checked, its
clock started after its one-off imports, and a plug-in's result checked.

Above every solver and below the SfM stack: it runs a solver by name, so it
imports the registry (:mod:`~mpe3d.solvers.base`) and the Eq. 1 stress that a
plug-in may leave for it to fill in.
"""

from __future__ import annotations

import importlib
import time
from typing import Any

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.options import INITS
from mpe3d.solvers.base import (
    Observations,
    Reconstruction,
    SolverSpec,
    check_observations,
    get_solver,
    validate_options,
)


def solve(name: str, observations: Observations, *, init: str = "smart",
          random_state: int | np.random.Generator | None = None,
          **options: Any) -> Reconstruction:
    """Run solver ``name`` on ``observations`` and time it.

    Parameters
    ----------
    name : str
        A registered solver (``mpe3d solvers`` lists them): ``sgd`` and
        ``baseline`` are the paper's, ``factorize`` and ``refine`` ours,
        and any plug-in's.
    observations : Observations
        The views, and the projections in the fixed setting.
    init : {"smart", "random"}, default "smart"
        The starting point, for solvers that take one (``sgd``); the others
        ignore it.
    random_state : int, Generator or None, default None
        Seeds everything random in the solver.
    **options
        The solver's options (``solver_options(name)``), checked against
        their declared rules.

    Returns
    -------
    Reconstruction
        ``runtime_s`` is the solver alone, validation excluded.
    """
    spec = get_solver(name)
    options = validate_options(name, options)
    check_observations(observations)
    setting = "fixed" if observations.fixed else "variable"
    if setting not in spec.settings:
        raise MpeError(f"solver '{name}' solves only the {' and '.join(spec.settings)} setting, "
                       f"not the {setting} one", key="projections")
    if spec.uses_init:
        INITS.check("init", init)
        options["init"] = init
    rng = np.random.default_rng(random_state)
    for module in spec.imports:  # outside the timed region
        importlib.import_module(module)
    from mpe3d.solvers import warmup

    # compiled, or loaded from numba's disk cache, before the clock too
    warmup.warm(options.get("loss", "l2"))
    start = time.perf_counter()
    result = spec.func(observations, random_state=rng, **options)
    runtime = time.perf_counter() - start
    if spec.origin is not None:  # a plug-in's result: what the harness relies on, checked
        result = _checked(spec, observations, result)
    result.runtime_s = runtime
    return result


def _checked(spec: SolverSpec, obs: Observations, result) -> Reconstruction:
    """A plug-in's result as the harness needs it, or one line saying what is wrong."""
    def fail(what: str) -> MpeError:
        return MpeError(f"solver '{spec.name}' ({spec.origin}) {what}")

    if not isinstance(result, Reconstruction):
        raise fail(f"returned a {type(result).__name__}, expected mpe3d.Reconstruction")
    points = np.asarray(result.points, dtype=float)
    projections = np.asarray(result.projections, dtype=float)
    if points.shape != (obs.n_points, 3):
        raise fail(f"returned points of shape {points.shape}, expected ({obs.n_points}, 3)")
    if projections.shape != (obs.n_views, 2, 3):
        raise fail(f"returned projections of shape {projections.shape}, expected ({obs.n_views}, 2, 3)")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(projections))):
        raise fail("returned NaN or inf in its points or projections")
    history = np.atleast_1d(np.asarray(result.stress_history, dtype=float))
    if result.stress is None:
        from mpe3d.solvers.stress import Stress

        result.stress = Stress(obs).value(points, projections)
    result.points, result.projections, result.stress_history = points, projections, history
    return result
