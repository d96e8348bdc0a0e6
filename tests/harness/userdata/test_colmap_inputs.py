"""COLMAP databases and photo sets as users have them: every camera model COLMAP
writes, several cameras in one database, scratch folders that are full, ids
past 2**31, and repeatable verification."""

import contextlib
import shutil
import sqlite3
import subprocess

import numpy as np
import pytest
from PIL import Image

from mpe3d.cli import main
from mpe3d.errors import MachineError, MpeError
from mpe3d.harness.scene import metrics, rendering, shapes
from mpe3d.harness.userdata import photos
from mpe3d.harness.userdata.reconstruct import prepare, reconstruct
from mpe3d.solvers.sfm import colmap, colmap_mapper
from mpe3d.solvers.sfm.tracks import Tracks
from tests.helpers import close_up_keypoints

pycolmap = pytest.importorskip("pycolmap")

PHOTOS = 12
SIZE = 320
SMALL = 224  # the second camera's photos: smaller, and a shorter focal length
SMALL_FOCAL = 0.55


@pytest.fixture(scope="module")
def spiral():
    return rendering.spiral_cameras(PHOTOS, size=SIZE, turns=0.5)


@pytest.fixture(scope="module")
def renders(spiral):
    """The chair through two cameras along one path: (big, small) images."""
    mesh = shapes.load_shape("chair")
    small = rendering.PhotoCameras(spiral.rotations, spiral.translations, spiral.focal * SMALL_FOCAL, SMALL, SMALL)
    return rendering.render(mesh, spiral, seed=1), rendering.render(mesh, small, seed=1)


def _pose_errors(result, spiral, names) -> np.ndarray:
    """COLMAP's benchmark's relative-pose errors (degrees) of ``result`` against the truth."""
    estimated = {c.view: (c.rotation, c.translation) for c in result.cameras if c.registered}
    truth = {name: (spiral.rotations[k], spiral.translations[k]) for k, name in enumerate(names)}
    return metrics.relative_pose_errors(truth, estimated)


@pytest.fixture(scope="module")
def two_cameras(renders, tmp_path_factory):
    """A database as COLMAP's extractor writes photos of two cameras (a camera per photo)."""
    folder = tmp_path_factory.mktemp("two") / "photos"
    folder.mkdir()
    names = []
    for k in range(PHOTOS):
        names.append(f"p{k:02d}.png")
        Image.fromarray(renders[k % 2][k]).save(folder / names[-1])
    database = folder.parent / "database.db"
    colmap.extract_and_match(database, folder, names)
    return database, names


def test_a_database_of_two_cameras_keeps_each_photos_camera(two_cameras, spiral):
    """Before, the first camera's principal point and one focal length went to
    every photo: exit 0 and poses 14.9 degrees off (median)."""
    database, names = two_cameras
    assert len(colmap.read_database(database, "raw").cameras) == PHOTOS  # one per photo, as COLMAP writes
    result = reconstruct(database)
    errors = _pose_errors(result, spiral, names)
    assert np.median(errors) < 3.0 and metrics.pose_auc(errors)["pose_auc10"] > 50, np.median(errors)  # 1.19, AUC@10 85
    assert any("2 cameras" in w for w in result.warnings)
    assert result.report["stages"][0]["stage"] == "cameras"
    focal = np.array([c.focal_px for c in result.cameras])
    assert np.allclose(focal[1::2] / focal[::2], SMALL_FOCAL, rtol=0.03)  # each photo its camera's
    for solver in ("colmap", "colmap_global"):  # COLMAP's mappers get a camera per group too
        mapped = reconstruct(database, solver=solver)
        assert sum(c.registered for c in mapped.cameras) >= 2


def _projection_misses(result, views) -> dict[str, float]:
    """Each registered view's median distance (px) from its reported P's image of
    the cloud to its keypoints in the photo's own pixels."""
    row = {str(i): k for k, i in enumerate(result.ids)}
    out = {}
    for camera, view in zip(result.cameras, views):
        keep = [j for j, i in enumerate(view["ids"]) if str(i) in row]
        X = result.points[[row[str(view["ids"][j])] for j in keep]]
        h = np.c_[X, np.ones(len(X))] @ camera.P.T
        own = np.asarray(view["xy"])[keep] + view.get("offset", (0.0, 0.0))
        out[camera.view] = float(np.median(np.linalg.norm(h[:, :2] / h[:, 2:] - own, axis=1)))
    return out


def test_each_photos_reported_camera_is_in_its_own_pixels(two_cameras, tmp_path):
    """Keypoints are solved round the first camera's principal point; the small
    camera's P gets its own back (48 px off before, the two principal points apart),
    and the exported model gives each photo its own size."""
    database, names = two_cameras
    views = photos.read_database(database)
    misses = _projection_misses(reconstruct(database), views)
    assert max(misses.values()) < 1.0, misses
    out = tmp_path / "model"
    assert main(["reconstruct", str(database), "--out", str(out)]) == 0
    model = colmap.read_model(out)
    sizes = {name: model.cameras[image.camera_id].width for name, image in model.images.items()}
    assert {sizes[n] for n in names[0::2]} == {SIZE} and {sizes[n] for n in names[1::2]} == {SMALL}


def test_cropped_photos_with_the_same_exif_get_their_own_focal_length(renders, spiral, tmp_path):
    """Every second photo cropped 320 -> 240 px, all with one EXIF focal length: COLMAP
    reads a focal length a quarter short for the crops. Fixing each camera's at its
    EXIF value gave 20.1 degrees median error; fitted per camera, it stays small."""
    folder = tmp_path / "cropped"
    folder.mkdir()
    names = [f"p{k:02d}.jpg" for k in range(PHOTOS)]
    for k, (name, image) in enumerate(zip(names, renders[0])):
        exif = Image.Exif()
        exif[0x010F], exif[0x0110] = "Maker", "Model"
        exif.get_ifd(0x8769)[0xA405] = int(round(spiral.focal / SIZE * 36))  # FocalLengthIn35mmFilm
        Image.fromarray(image[40:280, 40:280] if k % 2 else image).save(folder / name, quality=95,
                                                                         exif=exif.tobytes())
    database = tmp_path / "database.db"
    colmap.extract_and_match(database, folder, names)
    assert all(c.prior_focal for c in colmap.read_database(database, "raw").cameras.values())
    errors = _pose_errors(reconstruct(database), spiral, names)
    assert np.median(errors) < 3.0, np.median(errors)


def test_stale_matches_past_a_photos_keypoints_are_one_line(two_cameras, tmp_path, capsys):
    database = tmp_path / "database.db"
    shutil.copy(two_cameras[0], database)
    with pycolmap.Database.open(str(database)) as db:
        db.update_keypoints(1, np.asarray(db.read_keypoints(1))[:5])  # extracted again, the matches not
    assert main(["reconstruct", str(database), "--out", str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "p00.png and p01.png point past their keypoints" in err, err


def test_too_little_space_is_exit_3_wherever_tmpfs_cannot_be_mounted(two_cameras, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(colmap.shutil, "disk_usage", lambda where: shutil._ntuple_diskusage(10 ** 9, 10 ** 9, 2 ** 20))
    folder = two_cameras[0].parent / "photos"
    assert main(["reconstruct", str(folder), "--out", str(tmp_path / "c.ply")]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "(no --scratch given): 1 MB free, about " in err, err


def test_a_pinhole_database_of_non_square_pixels_reconstructs(renders, spiral, tmp_path):
    """PINHOLE (fx, fy): a traceback before (``camera.focal_length`` of two
    focal lengths); its pixels stretched here, so fx != fy and only its own
    parameters undo that."""
    folder = tmp_path / "stretched"
    folder.mkdir()
    names = [f"p{k:02d}.png" for k in range(PHOTOS)]
    height = SIZE * 3 // 4
    for name, image in zip(names, renders[0]):
        Image.fromarray(image).resize((SIZE, height), Image.BICUBIC).save(folder / name)
    camera = colmap.Camera("PINHOLE", SIZE, height, (spiral.focal, spiral.focal * 0.75, SIZE / 2, height / 2), True)
    database = tmp_path / "database.db"
    colmap.extract_and_match(database, folder, names, camera=camera)
    assert {c.model for c in colmap.read_database(database, "raw").cameras.values()} == {"PINHOLE"}
    errors = _pose_errors(reconstruct(database), spiral, names)
    assert np.median(errors) < 2.5, np.median(errors)  # 1.28 degrees


@pytest.mark.parametrize("model, params", [
    ("PINHOLE", (300.0, 240.0, 150.0, 110.0)),
    ("SIMPLE_RADIAL", (300.0, 150.0, 110.0, -0.2)),
    ("RADIAL", (300.0, 150.0, 110.0, -0.2, 0.05)),
    ("OPENCV", (300.0, 290.0, 150.0, 110.0, -0.1, 0.01, 0.002, -0.001)),
    ("SIMPLE_RADIAL_FISHEYE", (300.0, 150.0, 110.0, 0.05)),
])
def test_every_camera_model_is_taken_out_by_its_own_parameters(model, params):
    rng = np.random.default_rng(0)
    normalised = rng.uniform(-0.3, 0.3, (50, 2))
    camera = colmap.Camera(model, 300, 220, params)
    image = np.asarray(pycolmap.Camera(model=model, width=300, height=220, params=list(params)).img_from_cam(
        np.column_stack([normalised, np.ones(50)])))
    seen = camera.to_pinhole(image, 500.0, (10.0, 20.0))
    assert np.allclose(seen, 500.0 * normalised + (10.0, 20.0), atol=1e-6)


@pytest.mark.parametrize("change, message", [
    (lambda c: setattr(c, "width", 0), r"camera 1 \(SIMPLE_RADIAL, 0x320\): an image size of 0 pixels"),
    (lambda c: (setattr(c, "model", pycolmap.CameraModelId.EQUIRECTANGULAR), setattr(c, "params", [320.0, 320.0])),
     r"camera 1 \(EQUIRECTANGULAR, 320x320\): a spherical camera"),
])
def test_a_camera_mpe3d_cannot_model_is_one_line_naming_it(two_cameras, tmp_path, capsys, change, message):
    database = tmp_path / "database.db"
    shutil.copy(two_cameras[0], database)
    with pycolmap.Database.open(str(database)) as db:
        camera = db.read_camera(1)
        change(camera)
        db.update_camera(camera)
    assert main(["reconstruct", str(database), "--out", str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert pytest.importorskip("re").search(f"{database}: photo p00.png: {message}", err), err


@pytest.fixture
def tiny_disk(tmp_path):
    """A 1 MB tmpfs (skipped where mounting is refused)."""
    where = tmp_path / "tiny"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)],
                             capture_output=True).returncode == 0
    if not mounted:
        pytest.skip("cannot mount a tmpfs here")
    yield where
    subprocess.run(["umount", str(where)], check=False)


def test_a_full_scratch_folder_is_refused_before_colmap_writes(two_cameras, tiny_disk, tmp_path, capsys):
    """COLMAP aborts the whole process (SIGABRT) when the disk fills under its
    writer threads: the space is checked before it starts."""
    folder = two_cameras[0].parent / "photos"
    out = tmp_path / "c.ply"
    assert main(["reconstruct", str(folder), "--scratch", str(tiny_disk), "--out", str(out)]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--scratch {tiny_disk}: 1 MB free, about " in err, err
    assert "MB needed for the features and matches" in err and not out.exists()
    assert not list(tiny_disk.iterdir())
    with pytest.raises(MachineError, match="MB needed"):  # the tracks' database of COLMAP's mapper too
        reconstruct(close_up_keypoints(n=3000, views=40), solver="colmap", scratch=tiny_disk)


def test_a_scratch_that_is_no_folder_is_one_line(two_cameras, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    folder = two_cameras[0].parent / "photos"
    assert main(["reconstruct", str(folder), "--scratch", str(afile), "--out", str(tmp_path / "c.ply")]) == 2
    assert capsys.readouterr().err.strip() == f"mpe3d: error: --scratch {afile}: no such folder"


def test_verification_repeats_on_two_threads_with_a_seed(two_cameras, tmp_path):
    found = []
    for k in range(2):
        database = tmp_path / f"{k}.db"
        shutil.copy(two_cameras[0], database)
        with pycolmap.Database.open(str(database)) as db:
            db.clear_two_view_geometries()
        colmap.verify_matches(database, threads=2, seed=7)
        db = colmap.read_database(database, "verified")
        found.append({tuple(p): m.tobytes() for p, m in zip(db.pairs, db.matches)})
    assert found[0] == found[1] and len(found[0]) > 10


def test_track_labels_past_2_31_stay_apart():
    """csgraph's labels are int32; a label times 8 photos past 2**31 wrapped before."""
    label = np.array([2 ** 30, 2 ** 30, 2 ** 30 + 1, 2 ** 30 + 1], dtype=np.int32)
    image = np.array([0, 1, 3, 3])
    labels, counts = photos.photos_per_label(label, image, 8)
    assert labels.tolist() == [2 ** 30, 2 ** 30 + 1] and counts.tolist() == [2, 1]


def test_point_ids_past_2_31_survive_colmaps_mapper():
    views = close_up_keypoints(n=80, views=5)
    big = 2 ** 40 + 7 * np.arange(80, dtype=np.int64)
    result = reconstruct([{**v, "ids": big[v["ids"]]} for v in views], solver="colmap")
    assert set(result.ids.tolist()) <= set(big.tolist()) and len(result.ids) == 80


def test_what_colmap_cannot_read_is_one_line(tmp_path):
    bad = tmp_path / "database.db"
    bad.write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    with pytest.raises(MpeError, match=f"{bad}: not a readable SQLite file"):
        colmap.read_database(bad, "raw")
    other = tmp_path / "other.db"  # another program's SQLite file: refused, and left as it was
    with contextlib.closing(sqlite3.connect(other)) as db:
        db.execute("create table notes (text)")
        db.commit()
    before = other.read_bytes()
    with pytest.raises(MpeError, match=f"{other}: not a COLMAP database .no cameras, images, keypoints table."):
        colmap.read_database(other, "raw")
    assert other.read_bytes() == before


def test_seeds_past_colmaps_int32_are_folded(two_cameras, tmp_path):
    database = tmp_path / "database.db"
    shutil.copy(two_cameras[0], database)
    colmap.verify_matches(database, seed=2 ** 40 + 3)  # a traceback before: RANSAC's seed is an int32
    assert len(colmap.read_database(database, "verified").pairs)


def test_a_camera_none_of_whose_photos_registers_leaves_the_others(tmp_path):
    """COLMAP drops a camera that no registered photo uses: its views keep their start
    (a KeyError before)."""
    views = close_up_keypoints(n=120, views=6)
    rng = np.random.default_rng(1)
    for view in views[4:]:  # the second camera's photos: 12 keypoints that no pose explains
        view["ids"], view["xy"] = view["ids"][:12], rng.uniform(0, 400, (12, 2))
    result = colmap_mapper.colmap_map(Tracks.from_observations(prepare(views, solver="colmap").observations),
                                      view_cameras=np.array([0, 0, 0, 0, 1, 1]),
                                      image_size=np.full((6, 2), 400))
    assert result.registered[:4].all() and not result.registered[4:].any()
    assert np.all(np.isfinite(result.cameras.focal()))
