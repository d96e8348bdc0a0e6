import numpy as np

from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams
from tests.helpers import scene_and_observations


def test_solver_and_noise_do_not_change_the_scene():
    a = build_scene(make_config({"shape": "torus", "points": 100}))
    b = build_scene(make_config({"shape": "torus", "points": 100, "solver": "baseline",
                                 "noise.type": "distance", "noise.fraction": 0.5}))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.visible, b.visible)
    c = build_scene(make_config({"shape": "torus", "points": 100, "seed": 1}))
    assert not np.array_equal(a.points, c.points)


def test_observations_hold_no_ground_truth():
    config, scene, obs = scene_and_observations(points=80)
    assert obs.n_points == 80 and obs.n_views == 4
    assert np.array_equal(obs.visibility(), scene.visible)
    assert np.allclose(obs.projections, scene.projections)
    for view in obs.views:
        assert view.distances.shape == (view.size, view.size)
        assert np.allclose(view.distances, view.distances.T)
    assert scene.visible_per_view == [v.size for v in obs.views]
    variable = make_config({"shape": "torus", "points": 80, "projections": "variable"})
    obs_v, _ = observe(build_scene(variable), variable)
    assert obs_v.projections is None


def test_distance_noise_reaches_the_observations():
    _, _, clean = scene_and_observations(points=80)
    _, _, noisy = scene_and_observations(points=80, **{"noise.type": "distance",
                                                      "noise.fraction": 0.5})
    changed = [not np.allclose(a.distances, b.distances) for a, b in zip(clean.views, noisy.views)]
    assert all(changed)


def test_raytraced_views_record_counts():
    config = make_config({"shape": "chair", "points": 400, "visibility.mode": "raytrace"})
    scene = build_scene(config, seed_streams(0))
    counts = scene.visible_per_view
    assert len(counts) == 4 and all(0 < c < 400 for c in counts)


def test_min_views_keeps_exactly_the_points_seen_that_often():
    common = {"shape": "chair", "points": 600, "views": 5, "visibility.mode": "raytrace",
              "view_layout": "sphere"}
    everything = build_scene(make_config(common))
    seen = everything.visible.sum(axis=0)
    for m in (1, 3):
        subset = build_scene(make_config({**common, "visibility.min_views": m}))
        assert np.array_equal(subset.points, everything.points[seen >= m])
        assert subset.visible.sum(axis=0).min() >= m
    assert len(build_scene(make_config({**common, "visibility.min_views": 3})).points) < 600
