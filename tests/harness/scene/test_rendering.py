"""The photo renderer against the first one (benchmarks/render.py's reference): same bytes."""

import numpy as np

from mpe3d.harness.scene import rendering, shapes
from tests.helpers import load_script


def _reference():
    return load_script("benchmarks/render.py", "render_benchmark")


def test_compiled_value_noise_is_the_array_version_to_the_bit(rng):
    points = rng.uniform(-3.0, 3.0, size=(20_000, 3))  # negative cells too: the hash wraps
    for seed in (0, 5):
        assert np.array_equal(rendering.value_noise(points, seed), _reference().reference_noise(points, seed))


def test_photos_are_the_bytes_of_casting_every_ray():
    """Only rays inside the box round the projected mesh are cast; the photos
    (close and far views, a camera whose box crops the image) do not change."""
    mesh = shapes.load_shape("chair")
    for distance in (1.5, 0.75):  # 0.75: the chair overfills the photo
        cameras = rendering.spiral_cameras(4, size=64, distance=distance)
        got = rendering.render(mesh, cameras, seed=1)
        assert np.array_equal(got, _reference().reference_render(mesh, cameras, seed=1))
        assert np.count_nonzero(got) > 0.1 * got.size
