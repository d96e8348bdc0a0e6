import numpy as np
import trimesh

from mpe3d.harness.scene import visibility
from mpe3d.harness.scene.viewpoints import rotation


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


def test_the_zbuffer_keeps_the_nearest_point_on_each_ray():
    """The authors' definition on a scene checkable by hand: a view looking along
    +z sees point 1 behind point 0 (same image, farther), the opposite view sees
    it and not 0; points alone on their rays are seen from both."""
    points = np.array([[0, 0, 0.0], [0, 0, 1.0], [10, 10, 0.0], [10, 0, 5.0], [0, 10, 2.0]])
    opposite = np.diag([1.0, -1.0, -1.0])
    alpha = visibility.zbuffer(points, np.stack([np.eye(3), opposite]), n_rays=11)
    assert alpha.astype(int).tolist() == [[1, 0, 1, 1, 1], [0, 1, 1, 1, 1]]


def test_the_zbuffer_ray_takes_points_within_two_grid_spacings():
    """A far point ringed by nearer ones (11 rays over a 10-wide box: spacing 1).
    A ring of radius 1.9 reaches every ray within 2 spacings of the centre, so
    those rays keep ring points and the centre is hidden; at radius 2.1 the
    centre's own ray takes no ring point, and keeps the centre."""
    corners = np.array([[0, 0, 0.0], [10, 10, 0.0]])  # they fix the box
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    for radius, hidden in ((1.9, True), (2.1, False)):
        ring = np.column_stack([5 + radius * np.cos(angles), 5 + radius * np.sin(angles),
                                np.zeros_like(angles)])
        points = np.vstack([corners, ring, [[5, 5, 1.0]]])
        alpha = visibility.zbuffer(points, np.eye(3)[None], n_rays=11)[0]
        assert alpha[-1] == (not hidden)


def test_the_zbuffer_sees_nearly_every_point_of_a_dense_grid_and_few_of_a_sparse_one():
    from mpe3d.harness.experiment.config import make_config
    from mpe3d.harness.scene.observe import build_scene, seed_streams

    def share_in_three(n_rays):
        config = make_config({"shape": "chair", "points": 1024, "views": 4,
                              "visibility.mode": "zbuffer", "visibility.n_rays": n_rays})
        return (build_scene(config, seed_streams(0)).visible.sum(axis=0) >= 3).mean()
    assert share_in_three(None) > 0.95 > 0.5 > share_in_three(30)


def test_a_zbuffer_of_fewer_than_two_rays_is_refused():
    import pytest

    from mpe3d.errors import MpeError
    from mpe3d.harness.experiment.config import make_config
    with pytest.raises(MpeError, match="visibility.n_rays: must be at least 2"):
        make_config({"visibility.mode": "zbuffer", "visibility.n_rays": 1})
