import numpy as np
import pytest
import trimesh

from mpe3d.errors import MpeError
from mpe3d.harness.scene.shapes import PROCEDURAL, bundled_manifest, load_shape, sample_points


def test_bundle_covers_the_paper_categories():
    categories = {e["paper_category"] for e in bundled_manifest().values()}
    assert categories == {"airplane", "bench", "car", "chair", "lamp", "sofa", "table", "rifle"}
    for entry in bundled_manifest().values():
        assert entry["license"].startswith("CC0") or "CC0" in entry["license"]


@pytest.mark.parametrize("name", sorted(bundled_manifest()) + list(PROCEDURAL))
def test_every_shape_loads_normalised(name, rng):
    mesh = load_shape(name)
    lo, hi = mesh.bounds
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose((lo + hi) / 2, 0.0, atol=1e-9)
    pts = sample_points(mesh, 300, rng)
    assert pts.shape == (300, 3) and pts.dtype == np.float64


def test_sampling_is_area_uniform(rng):
    # a 1 x 1 x 0.01 slab: nearly all area is on the two big faces
    slab = trimesh.creation.box(extents=(1.0, 1.0, 0.01))
    pts = sample_points(slab, 20000, rng)
    on_big_faces = np.isclose(np.abs(pts[:, 2]), 0.005)
    assert abs(on_big_faces.mean() - 2 / 2.04) < 0.01


def test_mesh_paths_and_datasets(tmp_path, monkeypatch):
    box = trimesh.creation.box(extents=(2, 1, 1))
    box.export(tmp_path / "b.obj")
    assert len(load_shape(str(tmp_path / "b.obj")).faces) == 12
    shapenet = tmp_path / "sn" / "02691156" / "abc" / "models"
    shapenet.mkdir(parents=True)
    box.export(shapenet / "model_normalized.obj")
    monkeypatch.setenv("SHAPENET_DIR", str(tmp_path / "sn"))
    assert len(load_shape("shapenet:02691156/abc").faces) == 12
    pix = tmp_path / "pix" / "model" / "chair" / "IKEA_X"
    pix.mkdir(parents=True)
    box.export(pix / "model.obj")
    monkeypatch.setenv("PIX3D_DIR", str(tmp_path / "pix"))
    assert len(load_shape("pix3d:chair/IKEA_X").faces) == 12


def test_bad_shapes_say_why(tmp_path, monkeypatch):
    with pytest.raises(MpeError, match="unknown shape 'chiar' .*\\(did you mean 'chair'\\?\\)"):
        load_shape("chiar")
    with pytest.raises(MpeError, match="no mesh file"):
        load_shape(str(tmp_path / "missing.ply"))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"this is not a mesh")
    with pytest.raises(MpeError, match="cannot read|holds no triangles"):
        load_shape(str(bad))
    monkeypatch.delenv("SHAPENET_DIR", raising=False)
    with pytest.raises(MpeError, match="set \\$SHAPENET_DIR"):
        load_shape("shapenet:1/2")


def test_a_packaged_shape_is_read_once_and_handed_out_as_copies():
    first = load_shape("chair")
    first.apply_scale(3.0)  # a caller's change must not reach the next run
    again = load_shape("chair")
    assert again is not first
    assert np.isclose(np.linalg.norm(np.ptp(again.vertices, axis=0)), 1.0)
    assert np.array_equal(again.vertices, load_shape("chair").vertices)
