"""The common solver interface: observations in, a reconstruction out.

Every solver is a function ``solve(observations, *, init, random_state,
**options) -> Reconstruction`` registered under a name with :func:`register`.
Options are plain keyword arguments with defaults; :func:`validate_options`
checks ``solver.<option>`` keys against that signature, in one place.

Solvers import nothing from :mod:`harness` but :mod:`harness.errors` (the
error type and its message helpers): what they may see is exactly an
:class:`Observations`, which holds no ground truth.
"""

from __future__ import annotations

import inspect
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy.spatial.distance import cdist

from harness.errors import MpeError, coerce, suggest

from .linalg import classical_mds

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
    stress_history: np.ndarray  # stress per iteration (full batch)
    iterations: int
    termination: str
    runtime_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


SOLVERS: dict[str, Callable[..., Reconstruction]] = {}


def register(name: str):
    """Register ``func`` as solver ``name``; its keyword defaults are its options."""
    def decorator(func):
        SOLVERS[name] = func
        return func
    return decorator


def get_solver(name: str) -> Callable[..., Reconstruction]:
    if name not in SOLVERS:
        raise MpeError(f"unknown solver '{name}' (known: {', '.join(sorted(SOLVERS))})",
                       key="solver.name", hint=suggest(name, SOLVERS))
    return SOLVERS[name]


def solver_options(name: str) -> dict[str, Any]:
    """The options of solver ``name`` with their defaults."""
    params = inspect.signature(get_solver(name)).parameters
    return {p.name: p.default for p in params.values()
            if p.name not in _RESERVED and p.default is not inspect.Parameter.empty}


def validate_options(name: str, options: dict[str, Any]) -> dict[str, Any]:
    """Fill in defaults and check every ``solver.<option>`` of solver ``name``."""
    known = solver_options(name)
    out = dict(known)
    for key, value in options.items():
        if key not in known:
            listed = ", ".join(sorted(known)) or "none"
            raise MpeError(f"unknown option 'solver.{key}' for solver '{name}' (options: {listed})",
                           key=f"solver.{key}", hint=suggest(key, known))
        default = known[key]
        try:
            out[key] = value if default is None else coerce(f"solver.{key}", value, type(default))
        except MpeError:  # name the solver: the same option may differ between solvers
            raise MpeError(f"solver.{key}: expected {type(default).__name__} for solver '{name}', "
                           f"got {value!r}", key=f"solver.{key}") from None
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


def solve(name: str, observations: Observations, *, init: str = "smart",
          random_state: int | np.random.Generator | None = None,
          **options: Any) -> Reconstruction:
    """Run solver ``name`` and time it (``runtime_s`` is the solver alone)."""
    func = get_solver(name)
    options = validate_options(name, options)
    check_observations(observations)
    rng = np.random.default_rng(random_state)
    start = time.perf_counter()
    result = func(observations, init=init, random_state=rng, **options)
    result.runtime_s = time.perf_counter() - start
    return result
