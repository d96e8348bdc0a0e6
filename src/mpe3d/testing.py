"""Checks for the authors of solvers, as ``sklearn.utils.estimator_checks`` is
for estimators: hold your method to the contract every mpe3d solver keeps.

    from mpe3d.testing import check_sfm, check_solver

    def test_my_solver_keeps_the_contract():
        assert check_solver("mine") == []

    def test_my_sfm_method_keeps_the_contract():
        assert check_sfm("my_sfm") == []

The same checks run on the command line as ``mpe3d check-solver NAME``. What
each one asks is in :mod:`mpe3d.harness.experiment.contract` (stress solvers)
and :mod:`mpe3d.harness.experiment.sfm_contract` (SfM plug-ins).
"""

from mpe3d.harness.experiment.contract import Check, check_solver, run_checks
from mpe3d.harness.experiment.sfm_contract import check_sfm, run_sfm_checks

__all__ = ["Check", "check_sfm", "check_solver", "run_checks", "run_sfm_checks"]
