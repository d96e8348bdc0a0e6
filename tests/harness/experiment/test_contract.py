"""The public solver contract: every solver of ours passes it, and each way of
breaking it fails with the one line that says what to fix."""
import pytest

from mpe3d import solvers
from mpe3d.testing import check_solver
from tests.helpers import REPO, assert_contract_fails, run_cli

PLUGIN = REPO / "tests" / "plugins" / "avgmds.py"


@pytest.mark.parametrize("name", sorted(solvers.SOLVERS))
def test_every_solver_of_ours_keeps_the_public_contract(name):
    assert check_solver(name) == []


def broken(tmp_path, name, old, new):
    """The test plug-in, renamed and broken in one place."""
    text = PLUGIN.read_text().replace('"avgmds"', f'"{name}"').replace('"blobs"', f'"{name}_blobs"')
    assert old in text
    path = tmp_path / f"{name}.py"
    path.write_text(text.replace(old, new, 1))
    return path


BREAKS = {
    "wrong_shape": ("return Reconstruction(points=X,", "return Reconstruction(points=X.T,",
                    ["result (fixed): solver 'wrong_shape' (plug-in wrong_shape",
                     "returned points of shape (3, 60), expected (60, 3)"]),
    "no_seed": ("jitter * random_state.standard_normal", "(jitter + 0.01) * np.random.standard_normal",
                ["seed (fixed): two runs with random_state=0 differ",
                 "draw every random number from the random_state argument"]),
    "peeks": ("    n = observations.n_points", "    n = observations.n_points\n"
              "    getattr(observations, 'points', None)",
              ["observations only (fixed): reads observations.points: a solver may use only"]),
    "not_exact": ("summary=", "exact=True, summary=",
                  ["exact (fixed): it claims exact=True but misses a noise-free scene by"]),
    "bad_rule": ('{"jitter": Interval(float, 0, None)}', '{"jitter": Interval(float, 1, None)}',
                 ["options: solver.jitter's default 0.0 breaks its own rule (a number >= 1)"]),
    "distances_only": ("view.distance_matrix()", "view.distances",
                       ["views as coordinates (fixed): ",
                        "Error when views give 2D coordinates (observe=coordinates): use view.distance_matrix()"]),
}


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_each_broken_contract_is_one_line_saying_what_to_fix(tmp_path, name):
    old, new, expected = BREAKS[name]
    assert_contract_fails(check_solver, broken(tmp_path, name, old, new), name, expected)


def test_check_solver_on_the_command_line_exits_0_or_1(tmp_path):
    good = run_cli("check-solver", "avgmds", "--plugin", str(PLUGIN))
    assert good.returncode == 0, good.stdout + good.stderr
    assert good.stdout.strip().endswith("avgmds: 9 of 9 checks pass")
    bad = run_cli("check-solver", "peeks", "--plugin",
                  str(broken(tmp_path, "peeks", *BREAKS["peeks"][:2])))
    assert bad.returncode == 1 and "FAIL observations only (variable): reads observations.points" in bad.stdout
    assert bad.stdout.strip().endswith("peeks: 7 of 9 checks pass; 2 to fix")
    unknown = run_cli("check-solver", "nosuch")
    assert unknown.returncode == 2 and unknown.stderr.startswith("mpe3d: error: unknown solver 'nosuch'")
