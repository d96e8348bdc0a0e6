"""benchmarks/photos_vs_colmap.py: its rendered sets and references are the package's own."""
import sys

import numpy as np

from mpe3d.harness.scene import rendering
from tests.harness.userdata.test_references import write_bundler, write_colmap
from tests.helpers import REPO, load_script


def _benchmark():
    sys.path.insert(0, str(REPO / "benchmarks"))  # its `from machine import describe`
    try:
        return load_script("benchmarks/photos_vs_colmap.py", "photos_vs_colmap_benchmark")
    finally:
        sys.path.remove(str(REPO / "benchmarks"))


def test_a_rendered_set_has_the_photo_spirals_poses(tmp_path):
    images, truth = _benchmark().rendered("torus", 3, 1, tmp_path)
    cams = rendering.photo_spiral(3, 400, 1)
    assert sorted(p.name for p in images.iterdir()) == sorted(truth) == [f"image_{k:04d}.png" for k in range(3)]
    assert np.allclose(truth["image_0002.png"][0], cams.rotations[2])


def test_a_reference_is_read_as_mpe3d_reads_one(tmp_path):
    centres = np.array([[0.0, 0, -5], [1, 0, -5], [0, 1, -5]])
    R = rendering.look_at(centres)
    poses = {n: (R[k], -R[k] @ centres[k]) for k, n in enumerate(["a.png", "b.png", "c.png"])}
    for name, write in (("model", lambda f: write_colmap(f / "sparse" / "0", poses)),
                        ("bundler", lambda f: write_bundler(f / "bundle.out", list(poses.values())))):
        folder = tmp_path / name
        (folder / "images").mkdir(parents=True)
        for photo in poses:
            (folder / "images" / photo).write_bytes(b"")
        write(folder)
        found = _benchmark().reference(folder)
        assert sorted(found) == sorted(poses) and all(np.allclose(found[n][1], poses[n][1]) for n in poses)
