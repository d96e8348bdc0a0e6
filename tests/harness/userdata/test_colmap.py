"""Photos, COLMAP through pycolmap, and COLMAP models in and out of `mpe3d reconstruct`."""
import numpy as np
import pandas as pd
import pytest

from mpe3d.cli import main
from mpe3d.errors import MpeError
from mpe3d.harness.experiment import colmap_sfm
from mpe3d.harness.experiment.colmap_pipeline import model_misfit, seen_in_photos
from mpe3d.harness.scene import metrics, rendering, shapes
from mpe3d.harness.userdata import colmap_model
from mpe3d.harness.userdata.reconstruct import reconstruct
from mpe3d.harness.userdata.results import ViewCamera
from mpe3d.reports.claims import FAILS, HOLDS, colmap_fails_below
from mpe3d.solvers.sfm import colmap
from tests.helpers import close_up_keypoints, similarity_rms

pycolmap = pytest.importorskip("pycolmap")


def test_renderer_is_deterministic_per_seed_and_draws_the_mesh_where_the_cameras_see_it():
    mesh = shapes.load_shape("chair")
    cameras = rendering.spiral_cameras(3, size=96)
    first = rendering.render(mesh, cameras, seed=3)
    assert np.array_equal(first, rendering.render(mesh, cameras, seed=3))
    assert not np.array_equal(first, rendering.render(mesh, cameras, seed=4))  # another texture
    # Visible surface points project onto the object's pixels (not the black background):
    # the camera convention of the renderer and of PhotoCameras.project agree.
    points = shapes.sample_points(mesh, 400, np.random.default_rng(0))
    seen = seen_in_photos(mesh, points, cameras)
    pixels, _ = cameras.project(points)
    for k in range(len(cameras)):
        u, v = np.floor(pixels[k, seen[k]]).astype(int).T
        assert seen[k].sum() > 100 and np.mean(first[k, v, u] > 0) > 0.97


def test_spiral_cameras_look_at_the_object_with_image_y_down():
    cameras = rendering.spiral_cameras(8, size=200)
    R = cameras.rotations
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3)) and np.allclose(np.linalg.det(R), 1)
    pixel, depth = cameras.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.3, 0.0]]))
    assert np.allclose(pixel[:, 0], [100, 100]) and np.all(depth > 0)
    assert np.all(pixel[:, 1, 1] < pixel[:, 0, 1])  # up in the world is up in the image


def test_similarity_transform_recovers_a_similarity(rng):
    source = rng.normal(size=(30, 3))
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    target = 2.5 * source @ Q.T + [1.0, -2.0, 0.5]
    s, Q_fit, t = metrics.similarity_transform(source, target)
    assert s == pytest.approx(2.5, rel=1e-12) and np.allclose(Q_fit, Q, atol=1e-12)
    assert np.allclose(s * source @ Q_fit.T + t, target, atol=1e-12)


def test_emd_of_clouds_of_different_sizes_is_the_mean_transport_distance():
    a = np.zeros((2, 3))
    b = np.array([[1.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [3.0, 0, 0]])
    scores = metrics.earth_movers(a, b)
    assert scores["emd_mean"] == pytest.approx(2.0) and scores["emd"] == pytest.approx(4.0)


def _synthetic_model(folder, rng, n=300, views=8):
    mesh = shapes.load_shape("chair")
    X = shapes.sample_points(mesh, n, rng)
    cameras = rendering.spiral_cameras(views, size=400)
    uv, _ = cameras.project(X)
    seen = [rng.random(n) < 0.8 for _ in range(views)]
    observed = [{"name": f"img{k}.png", "ids": np.flatnonzero(keep) + 1, "xy": uv[k][keep]}
                for k, keep in enumerate(seen)]
    poses = [ViewCamera(f"img{k}.png", cameras.matrices()[k], cameras.rotations[k], cameras.focal,
                        cameras.translations[k]) for k in range(views)]
    colmap_model.write_model(folder, X, np.arange(1, n + 1), observed, poses, cameras.principal_point)
    return X


def _similarity_rms(X, Y):
    return similarity_rms(X, Y)


def _model_points(folder):
    model = pycolmap.Reconstruction(folder)
    ids = np.array(sorted(model.points3D))
    return ids, np.array([model.points3D[i].xyz for i in ids])


def test_a_colmap_model_round_trips_through_reconstruct_exactly(tmp_path, rng, capsys):
    X = _synthetic_model(tmp_path / "model", rng)
    assert main(["reconstruct", str(tmp_path / "model"), "--out", str(tmp_path / "cloud.csv")]) == 0
    cloud = pd.read_csv(tmp_path / "cloud.csv")
    assert _similarity_rms(cloud[["x", "y", "z"]].to_numpy(), X[cloud["id"] - 1]) < 1e-9
    assert "perspective camera" in capsys.readouterr().out
    # ... and out as a COLMAP model: the same points, tracks that reproject exactly
    assert main(["reconstruct", str(tmp_path / "model"), "--out", str(tmp_path / "out") + "/"]) == 0
    ids, Y = _model_points(tmp_path / "out")
    assert _similarity_rms(Y, X[ids - 1]) < 1e-9
    assert (tmp_path / "out" / "points3D.ply").is_file()
    model = pycolmap.Reconstruction(tmp_path / "out")
    errors = [np.linalg.norm(image.project_point(model.points3D[p.point3D_id].xyz) - p.xy)
              for image in model.images.values() for p in image.points2D if p.has_point3D()]
    assert len(errors) > 1000 and max(errors) < 1e-6
    # the written model reads back in, in text form too
    text = tmp_path / "text"
    text.mkdir()
    model.write_text(text)
    views = colmap_model.read_model(text)
    assert len(views) == 8 and all(np.all(v["ids"] >= 1) for v in views)


def test_distorted_cameras_are_taken_to_one_pinhole(tmp_path, rng):
    X = _synthetic_model(tmp_path / "model", rng, n=120, views=5)
    model = pycolmap.Reconstruction(tmp_path / "model")
    for camera in model.cameras.values():  # distort: k1 != 0, the keypoints moved to match
        f, _, cx, cy = camera.params
        distorted = pycolmap.Camera.create_from_model_name(camera.camera_id, "SIMPLE_RADIAL", f,
                                                           camera.width, camera.height)
        distorted.params = [f, cx, cy, 0.05]
        image = next(im for im in model.images.values() if im.camera_id == camera.camera_id)
        for p in image.points2D:
            p.xy = distorted.img_from_cam(np.append(camera.cam_from_img(p.xy), 1.0))
        model.cameras[camera.camera_id] = distorted
    model.write(tmp_path / "model")
    views = colmap_model.read_model(tmp_path / "model")
    from mpe3d import reconstruct

    result = reconstruct(views, camera="perspective")
    assert result.report["reprojection_rms_px"] < 1e-6
    assert _similarity_rms(result.points, X[result.ids - 1]) < 1e-8


@pytest.mark.parametrize("damage, message", [
    (lambda d: (d / "images.bin").unlink(), "an incomplete COLMAP model: images.bin missing"),
    (lambda d: (d / "points3D.bin").write_bytes(b"\x07" * 11), "points3D.bin: damaged (11 bytes"),
    (lambda d: (d / "images.bin").write_bytes((d / "images.bin").read_bytes()[:-9]),
     "COLMAP cannot read the model"),
    (lambda d: [p.unlink() for p in d.iterdir()] and (d / "cameras.txt").write_text("# x\n"),
     "an incomplete COLMAP model"),
])
def test_bad_model_folders_get_one_line(tmp_path, rng, capsys, damage, message):
    _synthetic_model(tmp_path / "model", rng, n=40, views=3)
    damage(tmp_path / "model")
    code = main(["reconstruct", str(tmp_path / "model"), "--out", str(tmp_path / "c.ply")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and not (tmp_path / "c.ply").exists()


def test_model_output_folder_is_checked_before_any_work(tmp_path, rng, capsys):
    _synthetic_model(tmp_path / "model", rng, n=40, views=3)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    code = main(["reconstruct", str(tmp_path / "model"), "--out", str(tmp_path / "busy")])
    assert code == 2 and "holds other files" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "busy").iterdir()) == ["notes.txt"]
    code = main(["reconstruct", str(tmp_path / "model"), "--out", str(tmp_path / "no" / "m") + "/"])
    assert code == 2 and "does not exist" in capsys.readouterr().err


def test_a_tiny_colmap_run_registers_photos_and_its_tracks_are_consistent(tmp_path):
    mesh = shapes.load_shape("chair")
    cameras = rendering.spiral_cameras(10, size=240, turns=0.5)  # 18 degrees apart
    names = rendering.save_images(rendering.render(mesh, cameras, seed=0), tmp_path / "images")
    sfm = colmap_sfm.run_sfm(tmp_path / "images", names, tmp_path, focal=cameras.focal,
                         principal_point=cameras.principal_point)
    assert len(sfm.registered) >= 3 and len(sfm.points) >= 50
    assert np.all(np.isfinite(sfm.points))
    tracks = colmap_sfm.database_tracks(sfm.database)
    assert tracks.n_tracks > 50 and tracks.views_per_track().min() >= 2
    photo_twice = pd.Series(tracks.image).groupby(tracks.track).apply(lambda s: s.duplicated().any())
    assert not photo_twice.any()
    assert len(colmap_sfm.triangulated(tracks, sfm)) > 0.5 * len(sfm.points)


def test_colmap_claim_reads_the_registered_share():
    frame = pd.DataFrame({"status": "FINISHED", "pipeline": "colmap", "images.count": [25, 50, 250],
                          "registered_share": [0.2, 0.3, 1.0], "solver.name": "sgd"})
    assert colmap_fails_below(frame, None).verdict == HOLDS
    frame["registered_share"] = [0.9, 0.3, 1.0]
    assert colmap_fails_below(frame, None, often=0.75).verdict == FAILS


def test_pycolmap_missing_is_one_line(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_pycolmap(name, *args, **kwargs):
        if name == "pycolmap":
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pycolmap)
    with pytest.raises(MpeError, match="pip install pycolmap"):
        colmap.version()


def test_the_colmap_keys_are_checked_and_leave_older_runs_hashes_alone():
    from mpe3d.harness.experiment.config import make_config

    before = make_config({"points": 256}).hash()
    assert make_config({"points": 256, "pipeline": "points", "images.count": 250}).hash() == before
    assert make_config({"pipeline": "colmap", "images.count": 25}).hash() != before
    for bad, message in [({"images.count": 1}, "images.count: must be at least 2"),
                         ({"images.size": 32}, "images.size: must be between 64 and 4096"),
                         ({"images.matching": "vocab"}, "images.matching: 'vocab' is not one of"),
                         ({"pipeline": "nerf"}, "pipeline: 'nerf' is not one of points, colmap")]:
        with pytest.raises(MpeError, match=message):
            make_config(bad)


def test_robust_similarity_ignores_a_minority_of_wild_pairs(rng):
    source = rng.normal(size=(200, 3))
    target = 3.0 * source + 1.0
    target[:30] += rng.normal(scale=50.0, size=(30, 3))  # 15 % far out
    s, Q, t = metrics.robust_similarity(source, target, np.random.default_rng(0))
    assert s == pytest.approx(3.0, rel=1e-9) and np.allclose(Q, np.eye(3), atol=1e-9)
    s_plain, _, _ = metrics.similarity_transform(source, target)
    assert abs(s_plain - 3.0) > 0.1  # what least squares alone makes of them


def test_the_tracks_feed_mpe3d_the_largest_group_of_photos_they_tie_together():
    from mpe3d.harness.userdata.photos import tied_views

    views = [{"name": f"a{k}", "ids": np.arange(10), "xy": np.zeros((10, 2))} for k in range(3)]
    views += [{"name": f"b{k}", "ids": np.arange(20, 30), "xy": np.zeros((10, 2))} for k in range(2)]
    views.insert(1, {"name": "c", "ids": np.array([0, 1, 20, 40]), "xy": np.zeros((4, 2))})
    assert [v["name"] for v in tied_views(views)] == ["a0", "a1", "a2"]


def test_model_misfit_is_what_the_pinhole_explains_and_weak_perspective_does_not():
    """COLMAP's tracks go to refine without its rejection rounds when bundle
    adjustment's pinhole fits them clearly better than weak perspective."""
    for orthographic, misfit in ((False, True), (True, False)):
        fit = reconstruct(close_up_keypoints(orthographic=orthographic), objective="reprojection",
                          camera="perspective", principal_point=(200.0, 200.0))
        assert model_misfit(fit.report) is misfit
