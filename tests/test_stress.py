import numpy as np
import pytest

from mpe3d.solvers.stress import Stress, project_rows

from .helpers import scene_and_observations


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
