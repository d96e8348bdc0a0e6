"""Solvers for the 3DMPE stress, behind one interface (see :mod:`mpe3d.solvers.base`).

The stress side (base, stress, its compiled kernels and point_kernels,
linalg, starts, the solvers; warmup, which compiles every kernel before a
solver's clock, and threads, the thread count their threaded passes may use,
at the bottom) imports nothing above it; :mod:`mpe3d.solvers.sfm`, the
keypoint stack, sits on top of it. Neither imports the harness or the reports.

May import: :mod:`mpe3d.options`, :mod:`mpe3d.plugins` and :mod:`mpe3d.errors`.
"""

from mpe3d.solvers import baseline, factorize, refine, sgd  # noqa: F401  (registration)
from mpe3d.solvers.base import (
                   SOLVERS,
                   Choice,
                   Interval,
                   Observations,
                   Reconstruction,
                   View,
                   check_observations,
                   get_solver,
                   register_solver,
                   solver_options,
                   validate_options,
)
from mpe3d.solvers.dispatch import solve

__all__ = ["Choice", "Interval", "Observations", "Reconstruction", "SOLVERS", "View",
           "check_observations", "get_solver", "register_solver", "solve", "solver_options",
           "validate_options"]
