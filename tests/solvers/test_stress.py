import os

import numpy as np
import pytest

from mpe3d.solvers import stress as stress_module
from mpe3d.solvers.stress import Stress, project_rows
from tests.helpers import exact_fma, scene_and_observations


def _numeric_grad(f, x, eps=1e-6):
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = eps
        g[idx] = (f(x + e) - f(x - e)) / (2 * eps)
    return g


def test_stress_is_zero_at_the_truth():
    _, scene, obs = scene_and_observations(points=60)
    S = Stress(obs)
    # not exactly zero: e^2 in Gram form rounds at ~1e-17 per entry (O(1) coordinates)
    assert S.value(scene.points, scene.projections) < 1e-12


def test_stress_counts_each_pair_once(rng):
    _, scene, obs = scene_and_observations(points=40, **{"visibility.mode": "all"})
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    expected = 0.0
    for k, view in enumerate(obs.views):
        Y = X[view.ids] @ scene.projections[k].T
        for i in range(view.size):
            for j in range(i):
                expected += (view.distances[i, j] - np.linalg.norm(Y[i] - Y[j])) ** 2
    assert Stress(obs).value(X, scene.projections) == pytest.approx(expected, rel=1e-10)


def test_gradients_match_finite_differences(rng):
    _, scene, obs = scene_and_observations(points=20, views=3)
    S = Stress(obs)
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    P = project_rows(scene.projections + 0.05 * rng.normal(size=scene.projections.shape))
    _, gX, gP = S.value_and_grad(X, P, want_P=True)
    # central differences with eps=1e-6 on O(1) values: error ~1e-8
    assert np.allclose(gX, _numeric_grad(lambda x: S.value(x, P), X), atol=1e-6)
    assert np.allclose(gP, _numeric_grad(lambda p: S.value(X, p), P), atol=1e-6)


def test_minibatch_masks_are_symmetric_and_drop_pairs(rng):
    _, scene, obs = scene_and_observations(points=200, **{"visibility.mode": "all"})
    S = Stress(obs)
    masks = S.sample_masks(0.3, rng)
    for m in masks:
        assert np.array_equal(m, m.T) and not m.diagonal().any()
        assert abs(m.mean() - 0.3) < 0.03
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    full = S.value(X, scene.projections)
    batch = S.value(X, scene.projections, masks)
    assert 0.2 * full < batch < 0.4 * full


def _with_coordinates(obs, X, P):
    """The same views given as 2D coordinates (the keypoints path)."""
    from mpe3d.solvers.base import Observations, View

    views = tuple(View(ids=v.ids, coordinates=X[v.ids] @ P[k].T) for k, v in enumerate(obs.views))
    return Observations(n_points=obs.n_points, views=views, projections=obs.projections)


def _relative_difference(a, b):
    worst = abs(a[0] - b[0]) / abs(b[0])
    for x, y in zip(a[1:], b[1:]):
        worst = max(worst, float(np.max(np.abs(x - y)) / np.max(np.abs(y))))
    return worst


@pytest.mark.parametrize("loss", ["l2", "huber", "soft_l1"])
@pytest.mark.parametrize("pairs", ["dense", "sparse"])
@pytest.mark.parametrize("extra", ["plain", "minibatch", "weights", "rejected", "rejected+weights"])
def test_the_compiled_kernel_matches_the_numpy_reference(rng, monkeypatch, loss, pairs, extra):
    from mpe3d.solvers import stress as stress_mod

    _, scene, obs = scene_and_observations(points=150, views=4)
    if pairs == "sparse":  # coordinates past the dense limit: scored on a sparse pair set
        monkeypatch.setattr(stress_mod, "DENSE_LIMIT", 20)
        obs = _with_coordinates(obs, scene.points, scene.projections)
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    P = project_rows(scene.projections + 0.05 * rng.normal(size=scene.projections.shape))
    compiled, numpy = (Stress(obs, loss, 0.02, kernel=k) for k in ("compiled", "numpy"))
    assert compiled.sparse == numpy.sparse == (pairs == "sparse")
    masks = compiled.sample_masks(0.4, rng) if extra == "minibatch" else None
    if extra != "plain" and extra != "minibatch":
        # "rejected": refine's alpha = 0 for 30% of the observations, 1 for the
        # rest (the compiled path drops those points from the view)
        alpha = [rng.uniform(0, 1, len(ids)) if extra != "rejected" else np.ones(len(ids))
                 for ids in obs_ids(obs)]
        if extra.startswith("rejected"):
            for a in alpha:
                a[rng.random(len(a)) < 0.3] = 0.0
        compiled, numpy = compiled.weighted(alpha), numpy.weighted(alpha)
        assert any(kept is not None for kept in compiled._kept) == (
            extra.startswith("rejected") and pairs == "dense")
    got = compiled.value_and_grad(X, P, masks, want_P=True)
    want = numpy.value_and_grad(X, P, masks, want_P=True)
    assert _relative_difference(got, want) <= 1e-12
    assert compiled.value(X, P, masks) == pytest.approx(want[0], rel=1e-12)


def obs_ids(obs):
    return [v.ids for v in obs.views]


def test_the_compiled_kernel_is_the_same_in_every_call(rng):
    """Serial loops in a fixed order: a repeat gives the same bits."""
    _, scene, obs = scene_and_observations(points=120)
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    first = Stress(obs).value_and_grad(X, scene.projections)
    again = Stress(obs).value_and_grad(X, scene.projections)
    assert first[0] == again[0] and np.array_equal(first[1], again[1])


def test_an_unknown_kernel_is_refused():
    _, _, obs = scene_and_observations(points=30)
    with pytest.raises(ValueError, match="kernel"):
        Stress(obs, kernel="fortran")


def test_kernels_index_nothing_out_of_bounds(tmp_path):
    """Under numba's bounds checking (NUMBA_BOUNDSCHECK=1, a debugging
    switch) every dense path runs: the loops index no empty array for the
    inputs they are not given."""
    import subprocess
    import sys

    code = """
import numpy as np
from mpe3d.solvers import kernels
rng = np.random.default_rng(0)
Y = rng.normal(size=(40, 2))
D = np.linalg.norm(Y[:, None] - Y[None], axis=2)
mask = np.triu(rng.random((40, 40)) < 0.5, 1)
mask = mask | mask.T
alpha = rng.uniform(size=40)
for m in (None, mask):
    for a in (None, alpha):
        for want in (False, True):
            kernels.view_stress(None, D, Y + 0.1, m, a, kernels.L2, 1.0, want)
kernels.smacof(D, rng.normal(size=(40, 3)), max_iter=3)
print("ok")
"""
    env = {**os.environ, "NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]


def _blas_chains_fused_multiply_adds() -> bool:
    """Whether numpy's BLAS sums a product as OpenBLAS's x86 AVX2 kernels do
    (one rounding per multiply-add, long sums in blocks of 256): then the
    one-call kernel must give numpy's bits, not just its values."""
    def fma_chain(a, b):
        total = 0.0
        for x, y in zip(a, b):
            total = exact_fma(x, y, total)
        return total

    rng = np.random.default_rng(0)
    G, X = rng.normal(size=(2, 300)), rng.normal(size=(300, 3))
    blocked = [fma_chain(G[0, :152], X[:152, c]) + fma_chain(G[0, 152:], X[152:, c]) for c in range(3)]
    return np.array_equal((G @ X)[0], blocked)


@pytest.mark.parametrize("weighted", [False, True])
def test_all_views_in_one_call_are_the_per_view_loop(rng, monkeypatch, weighted):
    # views of ~500 points: the pull-back's long sums run past one block of 256
    _, scene, obs = scene_and_observations(points=900, views=5, **{"visibility.mode": "exact",
                                                                   "visibility.k": 3})
    X = scene.points + 0.05 * rng.normal(size=scene.points.shape)
    P = project_rows(scene.projections + 0.05 * rng.normal(size=scene.projections.shape))

    def make():
        S = Stress(obs)
        if not weighted:
            return S
        # views 0-1 lose a fifth of their points (compacted), 2 almost none, 3 weighs some by 0.4
        alpha = [np.where(rng.random(len(ids)) < share, 0.0, 1.0)
                 for ids, share in zip(S.ids, (0.2, 0.2, 0.01, 0.0, 0.3))]
        alpha[3][::3] = 0.4
        return S.weighted(alpha)

    state = rng.bit_generator.state
    one_call = make()
    monkeypatch.setattr(stress_module, "PACK_LIMIT", -1)  # every view on its own
    rng.bit_generator.state = state
    per_view = make()
    same = np.array_equal if _blas_chains_fused_multiply_adds() else \
        (lambda a, b: np.allclose(a, b, rtol=1e-12, atol=1e-14 * np.abs(b).max()))
    for want_P in (True, False):
        v1, gX1, gP1 = one_call.value_and_grad(X, P, want_P=want_P)
        v2, gX2, gP2 = per_view.value_and_grad(X, P, want_P=want_P)
        assert same(v1, v2) and same(gX1, gX2)
        assert same(gP1, gP2) if want_P else gP1 is None and gP2 is None
    assert same(one_call.value(X, P), per_view.value(X, P))
