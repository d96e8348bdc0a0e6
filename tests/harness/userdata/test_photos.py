"""Photos and COLMAP databases into `mpe3d reconstruct`, and COLMAP's mapper as a method."""
import json

import numpy as np
import pytest
from PIL import Image

from mpe3d.cli import main
from mpe3d.errors import MpeError, Unregistered
from mpe3d.harness.scene import rendering, shapes
from mpe3d.harness.userdata import photo_folder, photos
from mpe3d.harness.userdata.formats import read_points
from mpe3d.harness.userdata.reconstruct import prepare, reconstruct
from mpe3d.solvers import threads
from mpe3d.solvers.sfm import colmap, colmap_mapper
from mpe3d.solvers.sfm.tracks import Tracks
from tests.helpers import close_up_keypoints, similarity_rms

pycolmap = pytest.importorskip("pycolmap")

PHOTOS = 12


@pytest.fixture(scope="module")
def shoot(tmp_path_factory):
    """A dozen photos of the chair along half a turn of the spiral (15 degrees
    apart, as photogrammetry guides ask), and their cameras."""
    folder = tmp_path_factory.mktemp("photos") / "chair"
    cameras = rendering.spiral_cameras(PHOTOS, size=320, turns=0.5)
    names = rendering.save_images(rendering.render(shapes.load_shape("chair"), cameras, seed=1), folder)
    return folder, dict(zip(names, cameras.centres))


@pytest.fixture(scope="module")
def database(shoot, tmp_path_factory):
    folder, _ = shoot
    path = tmp_path_factory.mktemp("db") / "database.db"
    colmap.extract_and_match(path, folder, photo_folder.list_photos(folder))
    return path


def _centre_error(report: dict, true_centres: dict) -> float:
    """RMS camera-centre error after a similarity, in % of the path's extent."""
    est, true = [], []
    for camera in report["cameras"]:
        if camera.get("registered", True):
            R, t = np.array(camera["rotation"]), np.array(camera["translation"])
            est.append(-R.T @ t)
            true.append(true_centres[camera["view"]])
    true = np.array(true)
    return 100 * similarity_rms(np.array(est), true) / np.linalg.norm(np.ptp(true, axis=0))


@pytest.mark.parametrize("solver, method", [("bundle", "bundle adjustment"), ("colmap", "COLMAP's incremental mapper"),
                                            ("colmap_global", "COLMAP's global mapper")])
def test_a_folder_of_photos_reconstructs_end_to_end(shoot, tmp_path, capsys, solver, method):
    folder, true_centres = shoot
    out, report = tmp_path / "cloud.csv", tmp_path / "report.json"
    runs = []
    with threads.limit(2):  # every COLMAP step that can take two does; the seed still repeats the run
        for _ in range(2):
            assert main(["reconstruct", str(folder), "--out", str(out), "--report", str(report),
                         "--solver", solver]) == 0
            runs.append(json.loads(report.read_text()))
    summary = runs[0]
    assert summary["cameras"] == runs[1]["cameras"] and summary["unplaced"] == runs[1]["unplaced"]
    assert summary["solver"] == solver and summary["objective"] == "reprojection"
    registered = [c for c in summary["cameras"] if c.get("registered", True)]
    assert len(registered) >= 8 and summary["points"] >= 200
    assert summary["reprojection_rms_px"] < 1.5
    assert _centre_error(summary, true_centres) < 2.0  # the cameras are where they were
    points, ids = read_points(out)
    assert len(points) == len(ids) == summary["points"]  # every track, its id beside it
    assert summary["unplaced"]["count"] < summary["points"] / 2
    assert method in capsys.readouterr().out
    if solver != "bundle":  # COLMAP's time split: its verification of the tracks' matches, then its mapper
        assert set(summary["colmap_seconds"]) == {"verify_s", "map_s"}


def test_a_photo_reconstruction_writes_a_colmap_model(shoot, tmp_path):
    folder, _ = shoot
    model = tmp_path / "model"
    assert main(["reconstruct", str(folder), "--out", str(model) + "/"]) == 0
    reread = pycolmap.Reconstruction(str(model))
    assert reread.num_reg_images() >= 8 and reread.num_points3D() >= 200


@pytest.mark.parametrize("matches", ["raw", "verified"])
def test_a_colmap_database_is_read_by_its_raw_or_verified_matches(database, tmp_path, matches):
    views = photos.read_database(database, matches)
    assert len(views) >= 8 and all(v["principal_point"] == (160.0, 160.0) for v in views)
    assert "focal_px" not in views[0]  # rendered PNGs carry no EXIF
    report = tmp_path / "r.json"
    assert main(["reconstruct", str(database), "--matches", matches, "--out", str(tmp_path / "c.csv"),
                 "--report", str(report)]) == 0
    assert json.loads(report.read_text())["reprojection_rms_px"] < 1.5


def test_two_threads_extract_match_and_verify_as_one_does(shoot, database, tmp_path):
    """The extractor's threads write the photos as they finish them: numbered
    again in name order, the pairs (and so RANSAC's samples) are the same."""
    folder, _ = shoot
    again = tmp_path / "again.db"
    colmap.extract_and_match(again, folder, photo_folder.list_photos(folder), threads=2)
    found = []
    for path in (database, again):
        with pycolmap.Database.open(str(path)) as db:
            images = sorted(db.read_all_images(), key=lambda im: im.image_id)
            pair_ids, geometries = db.read_two_view_geometries()
            found.append(([im.name for im in images], [im.camera_id for im in images],
                          sorted((p, g.inlier_matches.tobytes()) for p, g in zip(pair_ids, geometries))))
    assert found[0][0] == sorted(found[0][0]) and found[0][1] == list(range(1, len(found[0][1]) + 1))
    assert found[0] == found[1]


def test_a_database_written_out_of_name_order_is_numbered_in_it(tmp_path):
    """As the extractor's threads may leave it: photos written last name
    first, two cameras shared among them, descriptors and a pose prior."""
    names = [f"p{k}.jpg" for k in range(5)]
    cameras = [colmap.simple_camera("SIMPLE_RADIAL", 320, 240, f, (160.0, 120.0)) for f in (300.0, 500.0)]
    camera_of = np.array([0, 1, 0, 1, 1])  # of the names in the order written: last name first
    rng = np.random.default_rng(0)
    keypoints = [rng.uniform(0, 200, (10 + k, 2)) for k in range(5)]
    path = tmp_path / "database.db"
    colmap.write_database(path, names[::-1], cameras, camera_of, keypoints, np.zeros((0, 2), int), [])
    with pycolmap.Database.open(str(path)) as db:
        for image in db.read_all_images():
            db.write_descriptors(image.image_id, pycolmap.FeatureDescriptors(
                pycolmap.FeatureExtractorType.SIFT, np.full((db.num_keypoints_for_image(image.image_id), 128),
                                                            ord(image.name[1]), dtype=np.uint8)))
            if image.name == "p3.jpg":
                prior = pycolmap.PosePrior()
                prior.corr_data_id = pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA,
                                                                       image.camera_id), image.image_id)
                prior.position = np.array([48.1, 11.5, 520.0])
                db.write_pose_prior(prior)
    colmap._in_name_order(path)
    with pycolmap.Database.open(str(path)) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        assert [im.name for im in images] == names and [im.image_id for im in images] == [1, 2, 3, 4, 5]
        focal = {im.name: db.read_camera(im.camera_id).params[0] for im in images}
        assert focal == {"p4.jpg": 300.0, "p3.jpg": 500.0, "p2.jpg": 300.0, "p1.jpg": 500.0, "p0.jpg": 500.0}
        assert [im.camera_id for im in images] == [1, 1, 2, 1, 2]  # numbered by first use in name order
        for k, image in enumerate(images):
            assert np.array_equal(db.read_keypoints(image.image_id)[:, :2], keypoints[4 - k].astype(np.float32))
            descriptors = db.read_descriptors(image.image_id)
            assert descriptors.type == pycolmap.FeatureExtractorType.SIFT and np.all(descriptors.data == ord(f"{k}"))
            assert db.read_frame(image.frame_id).rig_id == image.camera_id
        (prior,) = db.read_all_pose_priors()
        assert prior.corr_data_id.id == 4 and np.allclose(prior.position, [48.1, 11.5, 520.0])
    assert [p.name for p in tmp_path.iterdir()] == ["database.db"]  # the copy replaced it


def test_raw_matches_hold_what_verification_threw_away(database):
    with pycolmap.Database.open(str(database)) as db:
        raw = sum(len(m) for m in db.read_all_matches()[1])
        verified = sum(len(g.inlier_matches) for g in db.read_two_view_geometries()[1])
    assert raw > verified > 0
    tracks = {kind: photos.match_tracks(database, kind) for kind in ("raw", "verified")}
    assert tracks["raw"].conflicting > tracks["verified"].conflicting  # wrong matches join tracks
    with pytest.raises(MpeError, match="matches: 'checked' is not one of raw, verified"):
        photos.match_tracks(database, "checked")


def _with_exif(source, folder, focal_35mm):
    folder.mkdir()
    for path in sorted(source.glob("*.png"))[:4]:
        image = Image.open(path).convert("L")
        exif = image.getexif()
        exif[0x010F], exif[0x0110] = "Maker", "Model"
        exif.get_ifd(0x8769)[0xA405] = focal_35mm  # FocalLengthIn35mmFilm
        image.save(folder / f"{path.stem}.jpg", exif=exif, quality=95)
    return folder


def test_an_exif_focal_length_is_kept_only_when_plausible(shoot, tmp_path):
    folder, _ = shoot
    facts = {}
    for focal_35mm in (40, 212):  # a normal lens; 5.9 times the image side, a stale tag
        photo_dir = _with_exif(folder, tmp_path / f"f{focal_35mm}", focal_35mm)
        database = tmp_path / f"f{focal_35mm}.db"
        colmap.extract_and_match(database, photo_dir, photo_folder.list_photos(photo_dir))
        facts[focal_35mm] = photos.read_database(database)[0]
    assert facts[40]["focal_px"] / 320 in photos.PLAUSIBLE_FOCAL
    assert "focal_px" not in facts[212]


@pytest.mark.parametrize("solver", ["colmap", "colmap_global"])
def test_colmap_solves_any_keypoint_input_with_the_users_ids(solver):
    views = close_up_keypoints(n=200, views=8)
    ids = np.arange(200) * 7 + 3  # ids of the user's, not row numbers
    views = [{"ids": ids[v["ids"]], "xy": v["xy"]} for v in views]
    result = reconstruct(views, solver=solver, principal_point=(200.0, 200.0))
    ours = reconstruct(views, principal_point=(200.0, 200.0))
    assert result.facts["solver"] == solver and set(result.ids) == set(ids)
    placed = ~np.isin(result.ids, result.unplaced)
    assert placed.sum() >= 180 and result.facts["reprojection_rms_px"] < 0.6
    row = {i: r for r, i in enumerate(ours.ids.tolist())}
    order = [row[i] for i in result.ids[placed].tolist()]
    assert similarity_rms(result.points[placed], ours.points[order]) < 1e-2 * np.ptp(ours.points)
    assert set(result.facts["colmap_seconds"]) == {"verify_s", "map_s"}


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_colmaps_mappers_repeat_with_a_seed_on_any_thread_count(mapper, monkeypatch):
    """Every random choice of COLMAP takes the seed, and its mappers run on
    one thread: the same seed, the same cameras and points to the last bit
    (module docstring of :mod:`mpe3d.solvers.sfm.colmap`)."""
    tracks = Tracks.from_observations(prepare(close_up_keypoints(n=200, views=8), solver="colmap").observations)
    real, asked = getattr(pycolmap, f"{mapper}_mapping"), []

    def mapping(*args, options, **kwargs):  # COLMAP's own mapper, its thread count noted
        asked.append(options.num_threads)
        return real(*args, options=options, **kwargs)

    monkeypatch.setattr(pycolmap, f"{mapper}_mapping", mapping)
    runs = [colmap_mapper.colmap_map(tracks, seed=3, threads=t, principal_point=(200.0, 200.0), mapper=mapper)
            for t in (1, 2)]
    assert asked == [1, 1]
    assert runs[0].registered.all() and f"COLMAP's {mapper} mapper" in runs[0].termination
    assert np.array_equal(runs[0].cameras.vector(), runs[1].cameras.vector())
    assert np.array_equal(runs[0].cameras.rotations, runs[1].cameras.rotations)
    assert np.array_equal(runs[0].points, runs[1].points)


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_tracks_colmap_cannot_register_are_unregistered(mapper):
    """12 tracks: every pair of views shares 12 matches, under the 15 inliers
    COLMAP's verification asks of a pair, so no mapper has a pair to start from."""
    tracks = Tracks.from_observations(prepare(close_up_keypoints(n=12, views=4), solver="colmap").observations)
    with pytest.raises(Unregistered, match=f"^COLMAP's {mapper} mapper registered no two views"):
        colmap_mapper.colmap_map(tracks, mapper=mapper)
    with pytest.raises(MpeError, match="^mapper: 'glomap' is not one of incremental, global"):
        colmap_mapper.colmap_map(tracks, mapper="glomap")


def test_track_matches_link_every_pair_of_a_tracks_observations():
    tracks = Tracks(view=np.array([0, 1, 2, 1, 2, 0]), point=np.array([0, 0, 0, 1, 1, 2]),
                    z=np.zeros((6, 2)), n_points=3, n_views=3)
    pairs, rows = colmap_mapper.track_matches(tracks)
    linked = sorted(tuple(sorted(r)) for r in rows.tolist())
    assert linked == [(0, 1), (0, 2), (1, 2), (3, 4)]
    assert np.all(pairs[:, 0] < pairs[:, 1]) and np.all(tracks.view[rows] == pairs)


@pytest.mark.parametrize("solver", ["colmap", "colmap_global"])
def test_colmap_refuses_what_it_cannot_be_asked(solver):
    views = close_up_keypoints(n=60, views=4)
    named = f"solver='{solver}': "
    for kwargs, message in (({"camera": "scaled"}, f"^camera='scaled': {named}COLMAP has no affine camera; its "
                                                   "mapper takes camera auto or radial or perspective$"),
                            ({"loss": "huber"}, f"^loss='huber': {named}bundle adjustment's; COLMAP's mapper has "
                                                "its own loss .a trivial one., so loss stays l2$"),
                            ({"start": "file"}, f"^start='file': {named}bundle adjustment's; .*, so start stays own$"),
                            ({"outlier_threshold": 5.0}, f"^outlier_threshold=5.0: {named}bundle adjustment's; "
                                                         "COLMAP's mapper has its own filter .4 px., so "
                                                         "outlier_threshold stays 20.0$"),
                            ({"objective": "stress"}, f"^solver='{solver}' minimises the reprojection error"),
                            ({"projections": np.tile(np.eye(3)[:2], (4, 1, 1))},
                             f"^views: solver='{solver}' estimates the cameras; known projections")):
        with pytest.raises(MpeError, match=message):
            reconstruct(views, solver=solver, **kwargs)
    with pytest.raises(MpeError, match="solver='sgd' is a stress solver"):
        reconstruct(views, solver="sgd", objective="reprojection")
    assert reconstruct(views, solver="sgd").objective == "stress"  # a stress solver named: the stress


def _unreadable(folder, shoot):
    (folder / "a.jpg").write_bytes(b"not a jpeg at all")
    (folder / "b.jpg").write_bytes(b"nor this")


def _one(folder, shoot):
    Image.fromarray(np.zeros((64, 64), dtype=np.uint8)).save(folder / "only.png")


def _blank(folder, shoot):  # nothing to match: no two photos share a keypoint
    rng = np.random.default_rng(0)
    for k in range(3):
        Image.fromarray(rng.integers(0, 255, (96, 96), dtype=np.uint8)).save(folder / f"{k}.png")


@pytest.mark.parametrize("make, message", [
    (lambda folder, shoot: None, "a folder input needs photos"),
    (_unreadable, r"0 usable photo\(s\) of 2, 2 skipped \(a.jpg: not an image; b.jpg: not an image\)"),
    (_one, r"1 usable photo\(s\) of 1, 0 skipped; reconstruction needs 2 or more"),
    (_blank, "holds no matches|share 3 or more tracks"),
])
def test_bad_photo_folders_get_one_line_and_nothing_written(tmp_path, capsys, shoot, make, message):
    folder = tmp_path / "photos"
    folder.mkdir()
    make(folder, shoot)
    out = tmp_path / "cloud.ply"
    assert main(["reconstruct", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and pytest.importorskip("re").search(message, err), err
    assert not out.exists()


def test_a_database_without_matches_is_one_line(shoot, tmp_path, capsys):
    folder, _ = shoot
    database = tmp_path / "database.db"
    pycolmap.extract_features(database, folder, image_names=photo_folder.list_photos(folder)[:3],
                              device=pycolmap.Device.cpu)
    out = tmp_path / "cloud.ply"
    assert main(["reconstruct", str(database), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "holds no matches" in err and not out.exists()


@pytest.mark.parametrize("solver", ["colmap", "colmap_global"])
def test_photos_colmap_cannot_register_are_one_line(tmp_path, capsys, solver):
    """Two photos of a flat wall of random texture, one turned: matches, no 3D."""
    folder = tmp_path / "wall"
    folder.mkdir()
    rng = np.random.default_rng(2)
    texture = np.kron(rng.integers(0, 255, (40, 40)), np.ones((6, 6))).astype(np.uint8)
    for k in range(3):
        Image.fromarray(np.roll(texture, 3 * k, axis=1)).save(folder / f"{k}.png")
    out = tmp_path / "cloud.ply"
    code = main(["reconstruct", str(folder), "--solver", solver, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and not out.exists(), err


def test_auto_keeps_the_lens_of_distorted_photos_and_none_of_undistorted_ones(shoot, tmp_path):
    """camera="auto" on rendered photos: through a lens of k1 = -0.3 (the
    object filling the frame, so its edges move by pixels) it keeps the
    radial camera, and recovers k1; without a lens, the plain pinhole."""
    spiral = rendering.spiral_cameras(10, size=320, turns=0.4, fill=1.6, distance=1.2)
    lens = rendering.PhotoCameras(spiral.rotations, spiral.translations, spiral.focal, spiral.width,
                               spiral.height, (-0.3, 0.0))
    folder = tmp_path / "lens"
    rendering.save_images(rendering.render(shapes.load_shape("chair"), lens, seed=2), folder)
    distorted = reconstruct(folder).report
    assert distorted["camera"] == "radial", [s["why"] for s in distorted["stages"] if s["stage"] == "lens"]
    assert distorted["cameras"][0]["k1"] == pytest.approx(-0.3, abs=0.1)
    plain = reconstruct(shoot[0]).report
    assert plain["camera"] == "perspective", [s["why"] for s in plain["stages"] if s["stage"] == "lens"]
