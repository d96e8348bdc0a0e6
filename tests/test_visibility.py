import numpy as np
import trimesh

from mpe3d.harness import visibility
from mpe3d.harness.views import rotation


def test_exact_visibility_counts(rng):
    alpha = visibility.exact(8, 1000, 3, rng)
    assert alpha.shape == (8, 1000)
    assert np.all(alpha.sum(axis=0) == 3)
    # views chosen uniformly: each view holds about 3/8 of the points
    assert np.all(np.abs(alpha.sum(axis=1) / 1000 - 3 / 8) < 0.06)


def test_count_visibility_keeps_theta_points(rng):
    alpha = visibility.count(5, 400, 123, rng)
    assert np.all(alpha.sum(axis=1) == 123)


def test_raytrace_hides_a_point_behind_a_box():
    box = trimesh.creation.box(extents=(1, 1, 1))
    R = np.eye(3)[None]  # camera looks along +z, so rays to it go along -z
    points = np.array([
        [0.0, 0.0, 2.0],    # the box lies between it and the camera: hidden
        [3.0, 0.0, 2.0],    # beside the box: visible
        [0.0, 0.0, -0.5],   # on the face towards the camera: visible
        [0.2, 0.1, 0.5],    # on the far face: hidden by the box itself
        [0.0, 0.0, -2.0],   # in front of the box: visible
    ])
    alpha = visibility.raytrace(box, points, R)
    assert alpha[0].tolist() == [False, True, True, False, True]


def test_raytrace_sees_about_half_of_a_sphere(rng):
    sphere = trimesh.creation.icosphere(subdivisions=4)
    points, _ = trimesh.sample.sample_surface(sphere, 2000, seed=rng)
    alpha = visibility.raytrace(sphere, points, np.stack([rotation(0.3, 0.2, 0.1)]))
    assert 0.45 < alpha.mean() < 0.55


def test_ray_casting_uses_embree():
    # embreex is a runtime dependency: without it trimesh silently falls back
    # to a pure-Python intersector that is orders of magnitude slower.
    box = trimesh.creation.box()
    assert type(box.ray).__module__.endswith("ray_pyembree")
