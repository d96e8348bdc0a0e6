"""The solver contract, checked the way scikit-learn's ``check_estimator``
checks an estimator: on small scenes of our own, through the same
:func:`~mpe3d.solvers.solve` a sweep uses.

A solver passes when, in every setting it declares, it returns finite
``(N, 3)`` points and ``(K, 2, 3)`` projections with orthonormal rows (the
given ones when they are fixed); its stress history means what ours does;
one seed gives one result, whatever numpy's global state; each option's rule
refuses a value outside it; it reads nothing of the observations but what
every solver is given; it takes views given as coordinates as well as
distances; and, if it claims ``exact``, it recovers a noise-free scene.
Each failure is one line that says what to fix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.execute import BLAS_THREADS
from mpe3d.harness.scene.metrics import align_rigid
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams
from mpe3d.solvers import Choice, Interval, Observations, View, get_solver, solve
from mpe3d.solvers.base import SolverSpec

SCENE = {"shape": "torus", "points": 60, "views": 5, "visibility.k": 3}
ORTHONORMAL = 1e-6  # |P P^T - I| at most
EXACT_ROA = 1e-6  # ROA on a noise-free scene, as a share of its diameter
SAME_STRESS = 1e-6  # relative: a reported stress against Eq. 1 of the result
# Two runs with one seed agree to this share of the cloud's extent: BLAS may
# round differently with the memory alignment of its arrays, which no seed fixes.
SAME_RUN = 1e-9
# What a solver may read: the fields and helpers every Observations and View has.
ALLOWED = {Observations: {"n_points", "views", "projections", "n_views", "fixed", "visibility"},
           View: {"ids", "distances", "coordinates", "size", "distance_matrix", "image"}}


@dataclass(frozen=True)
class Check:
    """One check of the contract: its name, and what to fix when it failed."""

    name: str
    passed: bool
    message: str = ""

    def line(self) -> str:
        return f"{'PASS' if self.passed else 'FAIL'} {self.name}" + (f": {self.message}" if self.message else "")


def check_solver(name: str, random_state: int = 0) -> list[str]:
    """The contract's failures for solver ``name``, a line each (empty: it passes).

    Use it in a test: ``assert check_solver("mine") == []``.
    """
    return [c.line() for c in run_checks(name, random_state) if not c.passed]


def run_checks(name: str, random_state: int = 0) -> list[Check]:
    """Every check of the contract for solver ``name`` (see the module doc)."""
    spec = get_solver(name)
    checks = [_options(spec)]
    with threadpool_limits(limits=BLAS_THREADS):  # as in a sweep: BLAS sums in one order
        for setting in spec.settings:
            checks += _in_setting(spec, setting, random_state)
    return checks


def _scene(setting: str, seed: int, **keys):
    config = make_config({**SCENE, "projections": setting, "seed": seed, **keys})
    streams = seed_streams(config["seed"])
    scene = build_scene(config, streams)
    return scene, observe(scene, config, streams)[0]


def _attempt(name: str, run: Callable[[], list[Check] | Check]) -> list[Check]:
    try:
        out = run()
    except MpeError as exc:
        return [Check(name, False, str(exc))]
    except Exception as exc:  # noqa: BLE001 - any error of the solver is a failed check
        return [Check(name, False, f"raised {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")]
    return out if isinstance(out, list) else [out]


def _in_setting(spec: SolverSpec, setting: str, seed: int) -> list[Check]:
    scene, obs = _scene(setting, seed)
    checks = _attempt(f"result ({setting})", lambda: _result(spec, obs))
    if not checks[-1].passed:  # the checks below would only repeat it
        return checks
    checks += _attempt(f"seed ({setting})", lambda: _determinism(spec, obs, seed))
    repeatable = checks[-1].passed
    checks += _attempt(f"observations only ({setting})",
                       lambda: _observations_only(spec, obs, seed, repeatable))
    _, by_coordinates = _scene(setting, seed, observe="coordinates")
    checks += _attempt(f"views as coordinates ({setting})",
                       lambda: _coordinates(spec, by_coordinates, seed))
    if spec.exact:
        checks += _attempt(f"exact ({setting})", lambda: _exact(spec, scene, obs, seed))
    return checks


def _result(spec: SolverSpec, obs: Observations) -> Check:
    rec = solve(spec.name, obs, random_state=0)  # shapes and finiteness: solve checks a plug-in's
    name = f"result ({'fixed' if obs.fixed else 'variable'})"
    P = np.asarray(rec.projections, dtype=float)
    if np.asarray(rec.points).shape != (obs.n_points, 3) or P.shape != (obs.n_views, 2, 3):
        return Check(name, False, f"points {np.shape(rec.points)} and projections {P.shape}; expected "
                     f"({obs.n_points}, 3) and ({obs.n_views}, 2, 3)")
    off = float(np.abs(P @ P.transpose(0, 2, 1) - np.eye(2)).max())
    if off > ORTHONORMAL:
        return Check(name, False, f"projections are not orthonormal (|P Pᵀ - I| = {off:.2g}): "
                     "return 2×3 matrices with orthonormal rows")
    if obs.fixed and not np.allclose(P, obs.projections, atol=1e-9):
        return Check(name, False, "the fixed setting's projections were changed: return the given ones")
    history = np.asarray(rec.stress_history, dtype=float)
    if history.ndim != 1 or len(history) != rec.iterations + 1:
        return Check(name, False, f"stress_history has {history.size} values for {rec.iterations} "
                     "iterations: give the objective at the start and after each iteration")
    if not np.all(np.isfinite(history)) or history.min() < 0:
        return Check(name, False, "stress_history holds a negative, NaN or inf value")
    from mpe3d.solvers.stress import Stress

    eq1 = Stress(obs).value(np.asarray(rec.points, dtype=float), P)
    if abs(float(rec.stress) - eq1) > SAME_STRESS * max(eq1, 1e-12) + 1e-12:
        return Check(name, False, f"stress {rec.stress:.6g} is not the Eq. 1 stress of the result "
                     f"({eq1:.6g}): leave stress=None and mpe3d computes it")
    if not isinstance(rec.termination, str):
        return Check(name, False, "termination must be a string saying why it stopped")
    return Check(name, True)


def _determinism(spec: SolverSpec, obs: Observations, seed: int) -> Check:
    name = f"seed ({'fixed' if obs.fixed else 'variable'})"
    np.random.seed(1)
    first = solve(spec.name, obs, random_state=seed).points
    np.random.seed(2)  # a solver drawing from numpy's global state now draws otherwise
    again = solve(spec.name, obs, random_state=seed).points
    if not _same(first, again):
        gap = float(np.nanmax(np.abs(np.asarray(first) - np.asarray(again))))
        return Check(name, False, f"two runs with random_state={seed} differ (by up to {gap:.2g}): "
                     "draw every random number from the random_state argument")
    return Check(name, True)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    extent = float(np.ptp(a, axis=0).max()) if a.size else 0.0
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= SAME_RUN * max(extent, 1e-300)))


def _out_of_range(rule: Interval | Choice):
    """A value the rule must refuse, or None when it refuses nothing of its kind."""
    if isinstance(rule, Choice):
        return "not-a-" + "-".join(rule.names)
    if rule.low is not None:
        return rule.kind(rule.low - 1) if rule.kind is int or rule.closed in ("both", "left") \
            else rule.low
    if rule.high is not None:
        return rule.kind(rule.high + 1) if rule.kind is int or rule.closed in ("both", "right") \
            else rule.high
    return None


def _options(spec: SolverSpec) -> Check:
    from mpe3d.solvers import validate_options

    for option, default in spec.options().items():
        rule = spec.constraints[option]
        if default not in rule:
            return Check("options", False, f"solver.{option}'s default {default!r} breaks its own "
                         f"rule ({rule})")
        bad = _out_of_range(rule)
        if bad is None:
            continue
        try:
            validate_options(spec.name, {option: bad})
        except MpeError:
            continue
        return Check("options", False, f"solver.{option}={bad!r} was accepted: its rule ({rule}) "
                     "must refuse it")
    return Check("options", True)


def _watched(obs: Observations, asked: set[str]) -> Observations:
    """``obs`` as a solver sees it, noting every attribute it asks for that no
    Observations or View has (a peek at something else)."""
    def watching(cls):
        allowed = ALLOWED[cls]

        class Watched(cls):
            def __getattribute__(self, attr):
                if not attr.startswith("__") and attr not in allowed:
                    asked.add(f"{'observations' if cls is Observations else 'view'}.{attr}")
                return super().__getattribute__(attr)
        return Watched

    views = tuple(watching(View)(v.ids, v.distances, v.coordinates) for v in obs.views)
    return watching(Observations)(obs.n_points, views, obs.projections)


def _observations_only(spec: SolverSpec, obs: Observations, seed: int, repeatable: bool) -> Check:
    name = f"observations only ({'fixed' if obs.fixed else 'variable'})"
    asked: set[str] = set()
    try:
        watched = solve(spec.name, _watched(obs, asked), random_state=seed).points
    except AttributeError:  # what it peeked at does not exist on a plain Observations either
        watched = None
    if asked:
        return Check(name, False, f"reads {', '.join(sorted(asked))}: a solver may use only "
                     "n_points, views (ids, distances or coordinates) and projections")
    plain = solve(spec.name, obs, random_state=seed).points
    if watched is None or (repeatable and not _same(plain, watched)):
        return Check(name, False, "the result depends on the observations' type or identity, not "
                     "only on their contents")
    return Check(name, True)


def _coordinates(spec: SolverSpec, obs: Observations, seed: int) -> Check:
    name = f"views as coordinates ({'fixed' if obs.fixed else 'variable'})"
    try:
        solve(spec.name, obs, random_state=seed)
    except MpeError as exc:
        return Check(name, False, f"{exc} (views given as 2D coordinates, observe=coordinates)")
    except Exception as exc:  # noqa: BLE001 - reported with what to do about it
        return Check(name, False, f"{type(exc).__name__} when views give 2D coordinates "
                     "(observe=coordinates): use view.distance_matrix() or view.image(), which "
                     "work for both, not view.distances")
    return Check(name, True)


def _exact(spec: SolverSpec, scene, obs: Observations, seed: int) -> Check:
    rec = solve(spec.name, obs, random_state=seed)
    truth = scene.points
    error = float(np.sqrt(np.mean(np.sum((align_rigid(rec.points, truth) - truth) ** 2, axis=1))))
    diameter = float(np.linalg.norm(truth.max(axis=0) - truth.min(axis=0)))
    name = f"exact ({'fixed' if obs.fixed else 'variable'})"
    if error > EXACT_ROA * diameter:
        return Check(name, False, f"it claims exact=True but misses a noise-free scene by "
                     f"{error / diameter:.2g} of its diameter: fix it, or register it without exact")
    return Check(name, True)
