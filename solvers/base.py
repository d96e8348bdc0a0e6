"""The common solver interface: observations in, a reconstruction out.

Every solver is a function ``solve(observations, *, random_state, [init,]
**options) -> Reconstruction`` registered under a name with :func:`register_solver`,
which also takes each option's rule (:class:`Interval`, :class:`Choice`),
declared next to the function as scikit-learn's ``_parameter_constraints``
are. Options are plain keyword arguments with defaults; :func:`validate_options`
checks ``solver.<option>`` keys against their types and rules, in one place.

Solvers import nothing from the harness, only :mod:`mpe3d.errors` (the error
type and its message helpers) and :mod:`mpe3d.plugins` (whose solver a name
is): what they may see is exactly an :class:`Observations`, which holds no
ground truth. :func:`mpe3d.solvers.dispatch.solve` runs one.
"""

from __future__ import annotations

import inspect
import os
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from mpe3d import plugins
from mpe3d.errors import MpeError, coerce, suggest
from mpe3d.options import PROJECTIONS, Choice, Interval
from mpe3d.plugins import Origin
from mpe3d.solvers.linalg import classical_mds

_RESERVED = ("observations", "init", "random_state")


@dataclass(frozen=True)
class View:
    """What one view shows: the ids of its visible points, and either their
    pairwise 2D distances (the paper's input) or their 2D coordinates (what a
    user with keypoints has; O(n) instead of O(n^2))."""

    ids: np.ndarray  # (n_k,) point ids, each once
    distances: np.ndarray | None = None  # (n_k, n_k) symmetric, zero diagonal
    coordinates: np.ndarray | None = None  # (n_k, 2), in any 2D frame of the view

    @property
    def size(self) -> int:
        return len(self.ids)

    def distance_matrix(self) -> np.ndarray:
        """D^k, given or computed from the coordinates."""
        if self.distances is not None:
            return self.distances
        from scipy.spatial.distance import cdist  # here: 0.3 s to import, keypoints never need it

        return cdist(self.coordinates, self.coordinates)

    def image(self, random_state=None) -> np.ndarray:
        """The view's centred 2D points, exact up to an O(2) transform: the
        coordinates themselves, or classical MDS of the distances (by Lanczos)."""
        if self.coordinates is not None:
            return self.coordinates - self.coordinates.mean(axis=0)
        return classical_mds(self.distances, 2, random_state)


@dataclass(frozen=True)
class Observations:
    """Everything a solver may use: the views and, when fixed, their projections.

    ``projections`` is ``(K, 2, 3)`` with orthonormal rows in the fixed setting
    and ``None`` in the variable one.
    """

    n_points: int
    views: tuple[View, ...]
    projections: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return len(self.views)

    @property
    def fixed(self) -> bool:
        return self.projections is not None

    def visibility(self) -> np.ndarray:
        """The visibility vectors alpha^k as a ``(K, N)`` boolean matrix."""
        alpha = np.zeros((self.n_views, self.n_points), dtype=bool)
        for k, view in enumerate(self.views):
            alpha[k, view.ids] = True
        return alpha


@dataclass
class Reconstruction:
    """A solver's result: 3D points, projections, and how it got there."""

    points: np.ndarray  # (N, 3)
    projections: np.ndarray  # (K, 2, 3)
    stress: float  # Eq. 1 stress of ``points`` and ``projections``
    # The solver's objective (Eq. 1, or its robust form for refine's robust
    # losses) at the start and after each iteration, over all pairs.
    stress_history: np.ndarray
    # Updates of the estimate by the iterative descent: len(stress_history) - 1
    # for every solver, so 0 for the closed-form ones (baseline, factorize).
    iterations: int
    termination: str
    runtime_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


SETTINGS = tuple(PROJECTIONS)  # given projections P^k, or estimated ones


@dataclass(frozen=True)
class SolverSpec:
    """A registered solver: its function, its options' rules, and whose it is.

    ``paper`` is True for the paper's methods (its SGD and its MDS baseline)
    and False for the others; ``uses_init`` says whether it takes a starting
    point (``init``), so that callers do not hand one to a solver that
    ignores it. ``settings`` are those it solves (fixed and/or variable
    projections); ``exact`` claims that it recovers a noise-free scene up to
    a rigid motion, which :func:`mpe3d.testing.check_solver` then checks.
    ``imports`` are the modules it imports when it runs, imported before its
    clock starts: a one-off import (scikit-learn's takes seconds on a cold
    worker) is no part of a solve's runtime. ``origin`` is the plug-in it
    came from (``None``: mpe3d's own).
    """

    name: str
    func: Callable[..., Reconstruction]
    constraints: dict[str, Interval | Choice]
    paper: bool
    summary: str
    uses_init: bool
    imports: tuple[str, ...] = ()
    settings: tuple[str, ...] = SETTINGS
    exact: bool = False
    origin: Origin | None = None

    def options(self) -> dict[str, Any]:
        """The options with their defaults, from the function's signature."""
        params = inspect.signature(self.func).parameters
        return {p.name: p.default for p in params.values()
                if p.name not in _RESERVED and p.default is not inspect.Parameter.empty}


SOLVERS: dict[str, SolverSpec] = {}
plugins.add_registry("solver", SOLVERS)


def register_solver(name: str, *, constraints: dict[str, Interval | Choice] | None = None,
                    summary: str = "", paper: bool = False, settings: tuple[str, ...] = SETTINGS,
                    exact: bool = False, imports: tuple[str, ...] = ()):
    """Register the decorated function as solver ``name`` (a decorator).

    The function is ``solve(observations, *, random_state, [init,] **options)
    -> Reconstruction``: it sees only the :class:`Observations`, draws every
    random number from ``random_state`` (a ``numpy.random.Generator``), and
    returns the points ``(N, 3)``, the projections ``(K, 2, 3)`` (the given
    ones in the fixed setting), ``stress_history`` (its objective at the start
    and after each iteration), ``iterations`` (``len(stress_history) - 1``)
    and ``termination``; ``stress`` may be left ``None``, and the Eq. 1 stress
    of the result is filled in. ``runtime_s`` is measured by :func:`solve`.

    Parameters
    ----------
    name : str
        The name sweeps and the command line use (``solver=name``).
    constraints : dict, default None
        Each keyword option's rule (:class:`Interval` or :class:`Choice`); it
        must cover every option, so that none goes unchecked.
    summary : str, default ""
        One line for ``mpe3d solvers`` and the reference docs.
    paper : bool, default False
        True only for the paper's own methods.
    settings : tuple of {"fixed", "variable"}, default both
        The settings it solves; the others are refused in one line.
    exact : bool, default False
        It recovers noise-free views exactly (checked by ``check-solver``).
    imports : tuple of str, default ()
        Modules it imports lazily: imported before its clock starts.
    """
    constraints = dict(constraints or {})
    unknown = set(settings) - set(SETTINGS) if settings else {"(none)"}
    if unknown:
        raise TypeError(f"solver {name}: settings must be some of {SETTINGS}, got {tuple(settings)}")

    def decorator(func):
        spec = SolverSpec(name, func, constraints, paper, summary,
                          "init" in inspect.signature(func).parameters, tuple(imports),
                          tuple(settings), exact)
        missing = set(spec.options()) ^ set(constraints)
        if missing:
            raise TypeError(f"solver {name}: options and constraints differ on {sorted(missing)}")
        origin = plugins.claim("solver", name, func)
        SOLVERS[name] = replace(spec, origin=origin)
        return func
    return decorator


def get_solver(name: str) -> SolverSpec:
    if name not in SOLVERS:
        plugins.load_entry_points()  # an installed plug-in's name: read them now, once
    if name not in SOLVERS:
        raise MpeError(f"unknown solver '{name}' (known: {', '.join(sorted(SOLVERS))})"
                       + plugins.failure_note("solver"), key="solver.name", hint=suggest(name, SOLVERS))
    return SOLVERS[name]


def solver_options(name: str) -> dict[str, Any]:
    """The options of solver ``name`` with their defaults."""
    return get_solver(name).options()


def validate_options(name: str, options: dict[str, Any]) -> dict[str, Any]:
    """Fill in defaults and check every ``solver.<option>`` of solver ``name``
    against its type (that of its default) and its declared rule."""
    spec = get_solver(name)
    known = spec.options()
    out = dict(known)
    for key, value in options.items():
        if key not in known:
            listed = ", ".join(sorted(known)) or "none"
            raise MpeError(f"unknown option 'solver.{key}' for solver '{name}' (options: {listed})",
                           key=f"solver.{key}", hint=suggest(key, known))
        rule = spec.constraints[key]
        try:
            out[key] = coerce(f"solver.{key}", value, type(known[key]))
        except MpeError:
            out[key] = None
        if out[key] is None or out[key] not in rule:
            # name the solver: the same option may differ between solvers
            raise MpeError(f"solver.{key}: expected {rule} for solver '{name}', got {value!r}",
                           key=f"solver.{key}") from None
    return out


def require_memory(nbytes: float, what: str) -> None:
    """Refuse, in one line, work whose arrays cannot fit in this machine's memory."""
    try:
        available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not a POSIX system: let numpy decide
        return
    if nbytes > available:
        need = nbytes / 2**30
        amount = f"{need:.0f}" if need < 1e6 else f"{need:.1e}"
        raise MpeError(f"{what} need about {amount} GiB, "
                       f"more than this machine's {available / 2**30:.0f} GiB")


def check_observations(obs: Observations) -> None:
    """Reject observations a solver cannot use, naming the view at fault."""
    if obs.n_views < 2:
        raise MpeError(f"need at least 2 views, got {obs.n_views}")
    for k, view in enumerate(obs.views):
        n = view.size
        if (view.distances is None) == (view.coordinates is None):
            raise MpeError(f"view {k}: give either distances or coordinates")
        data, what, shape = ((view.distances, "distance matrix", (n, n)) if view.coordinates is None
                             else (view.coordinates, "coordinates", (n, 2)))
        if data.shape != shape:
            raise MpeError(f"view {k}: {what} has shape {data.shape}, expected {shape}")
        if not np.all(np.isfinite(data)):
            raise MpeError(f"view {k}: {what} holds NaN or inf")
        if n and (view.ids.min() < 0 or view.ids.max() >= obs.n_points):
            raise MpeError(f"view {k}: point ids outside 0..{obs.n_points - 1}")
        if len(np.unique(view.ids)) != n:
            raise MpeError(f"view {k}: a point id appears twice")
    if obs.projections is not None and obs.projections.shape != (obs.n_views, 2, 3):
        raise MpeError(f"projections have shape {obs.projections.shape}, expected ({obs.n_views}, 2, 3)")
