"""Each key a reproduction depends on reaches the code it names, by its effect
on a real run: a run that quietly ignored init, align, the minibatch constant
c or the step rule would pass every accuracy test and still be wrong."""
import sys

import numpy as np
import pytest

from mpe3d import solvers
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.execute import run
from mpe3d.harness.scene.metrics import align_ransac4
from mpe3d.solvers.base import SOLVERS, register_solver
from tests.helpers import scene_and_observations

NOISY = {"shape": "chair", "points": 96, "views": 4, "projections": "variable",
         "noise.type": "distance", "noise.fraction": 0.3, "noise.amplitude": 0.05,
         "solver.name": "sgd", "solver.max_iter": 40}


def test_init_reaches_the_solver():
    smart = run(make_config({**NOISY, "init": "smart"})).reconstruction
    random = run(make_config({**NOISY, "init": "random"})).reconstruction
    # the random start is uniform in the unit cube, far from the MDS start's stress
    assert random.stress_history[0] > 2 * smart.stress_history[0]


def test_align_reaches_the_metrics():
    rigid = run(make_config({**NOISY, "align": "rigid"}))
    affine = run(make_config({**NOISY, "align": "ransac4"}))
    assert np.array_equal(rigid.reconstruction.points, affine.reconstruction.points)
    # an affine map can also stretch: it fits a noisy cloud at least as well, and differently
    assert affine.metrics["cd_x100"] != rigid.metrics["cd_x100"]
    assert affine.metrics["roa"] == rigid.metrics["roa"]  # ROA is always after rigid alignment


def _sgd(obs, **options):
    return solvers.solve("sgd", obs, random_state=0, max_iter=30, **options)


def test_sgd_minibatch_constant_c_changes_the_pairs_it_sees():
    _, _, obs = scene_and_observations(shape="chair", points=120, views=4)
    full, half = _sgd(obs, c=1.0), _sgd(obs, c=0.5)
    assert full.stress_history[0] == half.stress_history[0]  # the same start, scored in full
    # half the pairs give other gradients: another path from the first step on
    assert not np.isclose(full.stress_history[1], half.stress_history[1], rtol=1e-6)
    assert np.array_equal(_sgd(obs, c=0.5).points, half.points)  # and c alone made the difference


def test_sgd_step_rules_differ():
    _, _, obs = scene_and_observations(shape="chair", points=120, views=4, projections="variable")
    mm, bb = _sgd(obs, step="mm"), _sgd(obs, step="bb")
    assert mm.stress_history[0] == bb.stress_history[0]  # the same start
    assert not np.allclose(mm.stress_history[1:], bb.stress_history[1:len(mm.stress_history)])


def test_ransac4_keeps_its_best_trial_not_its_first(rng):
    truth = rng.normal(size=(200, 3))
    A = np.array([[1.2, 0.1, 0.0], [0.0, 0.8, 0.3], [0.2, 0.0, 1.1]])
    recon = (truth - 0.5) @ np.linalg.inv(A).T
    outliers = rng.choice(200, size=60, replace=False)  # misplaced, as a bad reconstruction's are
    recon[outliers] += rng.normal(scale=0.5, size=(60, 3))
    inliers = np.setdiff1d(np.arange(200), outliers)
    first = np.random.default_rng(7).choice(200, size=4, replace=False)
    assert np.isin(first, outliers).any()  # the first trial is a bad one
    aligned = align_ransac4(recon, truth, np.random.default_rng(7), trials=200)
    assert np.allclose(aligned[inliers], truth[inliers], atol=1e-8)


def test_lazy_imports_happen_before_the_clock(monkeypatch):
    seen = {}

    from mpe3d.solvers import warmup

    @register_solver("lazy-probe", constraints={}, paper=False, summary="test", imports=("colorsys",))
    def probe(observations, *, random_state=None):
        seen["imported"] = "colorsys" in sys.modules
        seen["compiled"] = warmup.warmed()
        return solvers.solve("factorize", observations, random_state=0)

    monkeypatch.delitem(sys.modules, "colorsys", raising=False)
    monkeypatch.setattr(warmup, "_DONE", set())
    try:
        _, _, obs = scene_and_observations(points=40, views=3)
        solvers.solve("lazy-probe", obs, random_state=0)
    finally:
        SOLVERS.pop("lazy-probe")
    assert seen["imported"]
    assert seen["compiled"]  # the stress kernels are compiled or loaded before the clock


@pytest.mark.parametrize("solver", ["sgd", "baseline", "refine"])
def test_a_solvers_runtime_is_its_solve(solver):
    result = run(make_config({**NOISY, "solver.name": solver}))
    assert 0 < result.metrics["runtime_s"] <= result.wall_s


def test_every_pipeline_name_has_a_pipeline():
    """The config's names and the registry agree, and each pipeline keeps the protocol."""
    from mpe3d.harness.experiment.config import KEYS, PIPELINE_NAMES
    from mpe3d.harness.experiment.execute import pipeline

    assert PIPELINE_NAMES == KEYS["pipeline"].choices
    for name in PIPELINE_NAMES:
        assert all(callable(getattr(pipeline(name), f, None)) for f in ("run", "title", "describe")), name
    with pytest.raises(MpeError, match="unknown pipeline 'nope'"):
        pipeline("nope")


def test_every_run_solves_with_one_blas_thread_even_after_an_import():
    """The BLAS limit is kept on every run, also for a library that an import
    made between runs (the scan of the loaded libraries is cached)."""
    from threadpoolctl import threadpool_info

    seen = []

    @register_solver("blas-probe", constraints={}, paper=False, summary="test")
    def probe(observations, *, random_state=None):
        seen.append({lib["filepath"]: lib["num_threads"] for lib in threadpool_info()})
        return solvers.solve("factorize", observations, random_state=0)

    config = make_config({"shape": "torus", "points": 40, "views": 3, "solver.name": "blas-probe"})
    try:
        run(config)
        import sklearn.utils._openmp_helpers  # noqa: F401 - scikit-learn's OpenMP runtime
        run(config)
    finally:
        SOLVERS.pop("blas-probe")
    assert all(n == 1 for libraries in seen for n in libraries.values()), seen
    assert any("omp" in path for path in seen[1]), seen[1]
