"""Solvers for the 3DMPE stress, behind one interface (see :mod:`mpe3d.solvers.base`)."""

from .base import (Observations, Reconstruction, SOLVERS, View, check_observations,
                   get_solver, register, solve, solver_options, validate_options)
from . import baseline, factorize, refine, sgd  # noqa: F401  (registration)

__all__ = ["Observations", "Reconstruction", "SOLVERS", "View", "check_observations",
           "get_solver", "register", "solve", "solver_options", "validate_options"]
