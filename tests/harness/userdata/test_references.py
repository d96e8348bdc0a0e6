"""Reference poses read from COLMAP models and Bundler files, and `mpe3d reconstruct --reference`."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mpe3d.cli import main
from mpe3d.errors import MpeError
from mpe3d.harness.scene import rendering, shapes
from mpe3d.harness.scene.metrics import pose_auc, score_poses
from mpe3d.harness.userdata.references import poses_of, read_reference, unscored
from mpe3d.harness.userdata.results import Result, ViewCamera
from mpe3d.solvers.sfm import colmap
from tests.harness import colmap_evaluation as colmap_eval

pycolmap = pytest.importorskip("pycolmap")

FLIP = np.diag([1.0, -1.0, -1.0])
NAMES = ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]


@pytest.fixture
def poses(rng):
    """Four cameras round the origin, looking at it (COLMAP's convention)."""
    centres = rng.normal(size=(4, 3)) + [0, 0, -5]
    R = rendering.look_at(centres)
    return {n: (R[k], -R[k] @ centres[k]) for k, n in enumerate(NAMES)}


def write_colmap(folder, poses, size=200, focal=300.0):
    camera = colmap.simple_camera("SIMPLE_PINHOLE", size, size, focal, (size / 2, size / 2))
    images = [colmap.PosedImage(n, camera, R, t, np.zeros((0, 2))) for n, (R, t) in poses.items()]
    colmap.write_model(folder, images, np.zeros(0, dtype=np.int64), np.zeros((0, 3)), {})
    return folder


def write_bundler(path, poses: list, focal=300.0, point=True):
    """A Bundler v0.3 file written here, not by mpe3d's writer: cameras in
    Bundler's frame (R_b = F R, t_b = F t), None an unregistered camera (all
    zeros), and one point seen by every registered camera (or none)."""
    lines = ["# Bundle file v0.3", f"{len(poses)} {int(point)}"]
    for pose in poses:
        R, t = (np.zeros((3, 3)), np.zeros(3)) if pose is None else (FLIP @ pose[0], FLIP @ pose[1])
        lines += [f"{0.0 if pose is None else focal:.17g} 0 0", *(" ".join(f"{v:.17g}" for v in row) for row in R),
                  " ".join(f"{v:.17g}" for v in t)]
    seen = [k for k, pose in enumerate(poses) if pose is not None]
    if point:
        lines += ["0 0 0", "128 128 128", " ".join([str(len(seen))] + [f"{k} {k} 1.5 -2.5" for k in seen])]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_bundlers_frame_and_colmaps_see_a_point_at_one_pixel(poses):
    """The flip the reader applies, checked on the formulas themselves:
    Bundler's p = -P / P_z with y up, COLMAP's p = P / P_z with y down."""
    X = np.array([0.3, -0.2, 0.1])
    for R, t in poses.values():
        P = FLIP @ R @ X + FLIP @ t  # Bundler's camera
        bundler_xy = (-P[:2] / P[2]) * [1, -1]
        Q = R @ X + t
        assert bundler_xy == pytest.approx(Q[:2] / Q[2])


@pytest.mark.parametrize("layout", ["sparse/0", "sparse", "."])
def test_a_colmap_model_is_read_from_its_folder_or_the_one_holding_it(poses, tmp_path, layout):
    write_colmap(tmp_path / layout, poses)
    reference = read_reference(tmp_path)
    assert sorted(reference.poses) == NAMES and reference.photos == 4
    for name, (R, t) in poses.items():
        assert reference.poses[name][0] == pytest.approx(R) and reference.poses[name][1] == pytest.approx(t)


def test_a_text_model_reads_as_the_binary_one(poses, tmp_path):
    binary = write_colmap(tmp_path / "bin", poses)
    text = tmp_path / "text"
    text.mkdir()
    pycolmap.Reconstruction(str(binary)).write_text(str(text))
    assert (text / "images.txt").exists() and not (text / "images.bin").exists()
    a, b = read_reference(binary), read_reference(text)
    assert all(np.allclose(a.poses[n][0], b.poses[n][0]) and np.allclose(a.poses[n][1], b.poses[n][1])
               for n in NAMES)


def test_a_bundler_file_named_by_its_list_scores_100_against_the_same_colmap_poses(poses, tmp_path):
    model = read_reference(write_colmap(tmp_path / "sparse", poses))
    folder = tmp_path / "bundler"
    folder.mkdir()
    order = ["c.jpg", "a.jpg", "d.jpg", "b.jpg"]  # list.txt's order, not the names'
    (folder / "list.txt").write_text("".join(f"images/{n} 0 300.0\n" for n in order))
    reference = read_reference(write_bundler(folder / "bundle.out", [poses[n] for n in order]))
    assert sorted(reference.poses) == NAMES and reference.photos == 4 and reference.unposed == ()
    scores = score_poses(reference, model.poses)
    assert scores["pose_auc1"] == pytest.approx(100, abs=1e-4) and scores["registered"] == 4


def test_without_a_list_the_photos_name_the_cameras_in_name_order(poses, tmp_path):
    path = write_bundler(tmp_path / "bundle.out", [poses[n] for n in NAMES])
    reference = read_reference(path, photo_names=reversed(NAMES))
    assert all(np.allclose(reference.poses[n][0], poses[n][0]) for n in NAMES)
    with pytest.raises(MpeError, match="no list.txt beside it to name its 4 cameras"):
        read_reference(path)


def test_an_unregistered_bundler_camera_is_listed_not_posed(poses, tmp_path):
    path = write_bundler(tmp_path / "bundle.out", [poses["a.jpg"], None, poses["c.jpg"], poses["d.jpg"]])
    reference = read_reference(path, photo_names=NAMES)
    assert sorted(reference.poses) == ["a.jpg", "c.jpg", "d.jpg"]
    assert reference.unposed == ("b.jpg",) and reference.photos == 4
    scores = score_poses(reference, {n: poses[n] for n in ["a.jpg", "c.jpg", "d.jpg"]})
    assert scores["registered"] == 3 and scores["registered_fraction"] == 0.75
    assert scores["pose_auc3"] == pytest.approx(100, abs=1e-4)  # the reference has no pair with b.jpg


def _garbage_model(tmp_path):
    folder = tmp_path / "sparse"
    folder.mkdir()
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (folder / name).write_bytes(b"\x07" * 5)
    return tmp_path


def _short_list(tmp_path, poses=None):
    (tmp_path / "list.txt").write_text("a.jpg\nb.jpg\n")
    return write_bundler(tmp_path / "bundle.out", [None, None, None])


@pytest.mark.parametrize("make, message", [
    (lambda p: p / "nowhere", "no such file or folder"),
    (lambda p: p, "no COLMAP model in it or in sparse/0 or sparse"),
    (_garbage_model, "COLMAP cannot read the model"),
    (_short_list, "list.txt: 2 photo names for the 3 cameras of"),
    (lambda p: (p / "x.out").write_text("1 2 3\n") and p / "x.out", "not a Bundler .out file"),
])
def test_bad_references_are_one_line_naming_the_file(tmp_path, make, message):
    path = make(tmp_path)
    with pytest.raises(MpeError, match=message) as caught:
        read_reference(path)
    assert str(tmp_path) in str(caught.value) and "\n" not in str(caught.value)


def test_poses_of_keeps_registered_pinholes_only(poses):
    R, t = poses["a.jpg"]
    cameras = (ViewCamera("a.jpg", np.zeros((3, 4)), rotation=R, focal_px=300.0, translation=t),
               ViewCamera("b.jpg", np.zeros((2, 3)), rotation=R, scale=1.0, translation_px=np.zeros(2)),
               ViewCamera("c.jpg", np.full((3, 4), np.nan), registered=False))
    result = Result(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2, 3)), cameras=cameras)
    assert list(poses_of(result)) == ["a.jpg"]
    assert unscored(result).startswith("1 registered views have an affine camera")
    assert unscored(Result(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2, 3)), cameras=cameras[::2])) is None


def test_an_affine_camera_scored_against_a_reference_says_why_it_scores_nothing(rendered, tmp_path, capsys):
    folder, _ = rendered
    report = tmp_path / "r.json"
    assert main(["reconstruct", str(folder / "images"), "--reference", str(folder / "sparse" / "0"),
                 "--camera", "scaled", "--out", str(tmp_path / "c.csv"), "--report", str(report)]) == 0
    scores = json.loads(report.read_text())["reference"]
    assert scores["registered"] == 0 and scores["pose_auc3"] == 0
    assert "6 registered views have an affine camera" in capsys.readouterr().err


# -- the command line, on rendered photos ---------------------------------------------

@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Six 300-px photos of the chair along a sixth of a turn, and the exact
    reference: the rendering's cameras as a COLMAP model beside them."""
    folder = tmp_path_factory.mktemp("rendered")
    cameras = rendering.spiral_cameras(6, size=300, turns=6 / 25)
    names = rendering.save_images(rendering.render(shapes.load_shape("chair"), cameras, seed=1), folder / "images")
    poses = {n: (R, t) for n, R, t in zip(names, cameras.rotations, cameras.translations)}
    write_colmap(folder / "sparse" / "0", poses, size=300, focal=cameras.focal)
    return folder, poses


def test_reconstruct_scores_its_cameras_as_colmaps_benchmark_does_on_the_model_it_wrote(rendered, tmp_path,
                                                                                        capsys):
    folder, truth = rendered
    model, report = tmp_path / "M", tmp_path / "r.json"
    assert main(["reconstruct", str(folder / "images"), "--reference", str(folder), "--out", f"{model}/",
                 "--report", str(report)]) == 0
    scores = json.loads(report.read_text())["reference"]
    written = pycolmap.Reconstruction(str(model))
    estimated = {im.name: (im.cam_from_world().rotation.matrix(), im.cam_from_world().translation)
                 for im in written.images.values() if im.has_pose}
    recomputed = colmap_eval.compute_auc(colmap_eval.compute_grouped_rel_errors(truth, estimated), [3])[0]
    assert scores["pose_auc3"] == pytest.approx(recomputed, abs=0.5)
    assert scores["pose_auc3"] > 70  # 84.7: exact reference, 300-px photos 10 degrees apart
    assert scores["registered"] == len(estimated) and scores["photos"] == 6
    assert scores["source"] == str(folder / "sparse" / "0") and scores["centre_error"] < 2.0
    out = capsys.readouterr().out
    assert f"pose AUC@3 {scores['pose_auc3']:.1f}" in out and f"{len(estimated)}/6 photos registered" in out


@pytest.mark.parametrize("reference, message", [
    ("nowhere", "--reference .*nowhere: no such file or folder"),
    (".", "--reference .*: no COLMAP model in it"),
])
def test_a_bad_reference_fails_before_any_photo_is_read(rendered, tmp_path, capsys, reference, message):
    folder, _ = rendered
    out = tmp_path / "cloud.ply"
    assert main(["reconstruct", str(folder / "images"), "--reference", str(tmp_path / reference),
                 "--out", str(out), "--scratch", str(tmp_path / "scratch")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and pytest.importorskip("re").search(message, err), err
    assert not out.exists() and not (tmp_path / "scratch").exists()


def test_the_auc_recomputed_matches_pose_auc():
    """The transcription and mpe3d agree on the AUC of one set of errors (the end-to-end test leans on it)."""
    errors = np.array([0.2, 0.7, 2.5, 4.0, 12.0, 180.0])
    assert list(pose_auc(errors).values()) == pytest.approx(colmap_eval.compute_auc(errors, [1, 3, 5, 10]))


def test_poses_rotate_by_rotation_matrix_of_cam_from_world():
    """pycolmap's Rigid3d holds cam_from_world: the R, t of x_cam = R x + t the reader returns."""
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    pose = pycolmap.Rigid3d(np.column_stack([R, [1.0, 2.0, 3.0]]))
    assert pose.rotation.matrix() == pytest.approx(R) and pose * np.zeros(3) == pytest.approx([1, 2, 3])


# -- Done when: every solver, photos of two cameras and sizes, COLMAP and Bundler references -------

TWO = 12  # photos, alternately of a 320-px camera and a 224-px one of a shorter focal length


@pytest.fixture(scope="module")
def two_camera_sets(tmp_path_factory):
    """The same photos of two cameras twice: with the rendering's poses as a
    COLMAP model (sparse/0), and as a Bundler file named by its list.txt."""
    from PIL import Image

    spiral = rendering.spiral_cameras(TWO, size=320, turns=0.5)
    small = rendering.PhotoCameras(spiral.rotations, spiral.translations, spiral.focal * 0.55, 224, 224)
    mesh = shapes.load_shape("chair")
    renders = rendering.render(mesh, spiral, seed=1), rendering.render(mesh, small, seed=1)
    root = tmp_path_factory.mktemp("two")
    names = [f"p{k:02d}.png" for k in range(TWO)]
    for kind in ("colmap", "bundler"):
        (root / kind / "images").mkdir(parents=True)
        for k, name in enumerate(names):
            Image.fromarray(renders[k % 2][k]).save(root / kind / "images" / name)
    poses = {n: (spiral.rotations[k], spiral.translations[k]) for k, n in enumerate(names)}
    write_colmap(root / "colmap" / "sparse" / "0", poses, size=320, focal=spiral.focal)
    write_bundler(root / "bundler" / "bundle.out", [poses[n] for n in reversed(names)], focal=spiral.focal)
    (root / "bundler" / "list.txt").write_text("".join(f"images/{n} 0 {spiral.focal}\n" for n in reversed(names)))
    return root, poses


def _reconstruct_scored(folder, reference, solver, tmp_path, capsys):
    model, report = tmp_path / "M", tmp_path / "r.json"
    assert main(["reconstruct", str(folder / "images"), "--reference", str(reference), "--out", f"{model}/",
                 "--report", str(report), "--solver", solver]) == 0
    capsys.readouterr()
    written = pycolmap.Reconstruction(str(model))
    estimated = {im.name: (im.cam_from_world().rotation.matrix(), im.cam_from_world().translation)
                 for im in written.images.values() if im.has_pose}
    return json.loads(report.read_text())["reference"], estimated


@pytest.mark.parametrize("solver", ["bundle", pytest.param("colmap", marks=pytest.mark.slow),
                                    pytest.param("colmap_global", marks=pytest.mark.slow)])
@pytest.mark.parametrize("kind", ["colmap", pytest.param("bundler", marks=pytest.mark.slow)])
def test_every_solver_is_scored_as_colmaps_benchmark_scores_the_model_it_wrote(two_camera_sets, tmp_path, capsys,
                                                                                solver, kind):
    root, truth = two_camera_sets
    reference = root / kind / ("sparse/0" if kind == "colmap" else "bundle.out")
    scores, estimated = _reconstruct_scored(root / kind, reference, solver, tmp_path, capsys)
    recomputed = colmap_eval.compute_auc(colmap_eval.compute_grouped_rel_errors(truth, estimated), [3])[0]
    assert scores["pose_auc3"] == pytest.approx(recomputed, abs=0.5)
    assert scores["photos"] == TWO and scores["registered"] == len(estimated) >= 2
    if solver == "bundle":  # ours registers every photo of two cameras (1.2 degrees median, AUC@3 ~52)
        assert scores["registered"] == TWO and scores["pose_auc3"] > 30


def test_a_reference_naming_none_of_the_photos_is_one_line_and_a_partial_one_a_note(poses, tmp_path):
    model = write_colmap(tmp_path / "sparse" / "0", poses)
    with pytest.raises(MpeError, match=r"none of its 4 photos is among the 2 photos given \(it names e.g. 'a.jpg', "
                                       r"the photos e.g. 'A.JPG'\)"):
        read_reference(model, ["A.JPG", "B.JPG"])
    partial = read_reference(model, ["a.jpg", "b.jpg", "c.jpg", "x.jpg"])
    assert partial.notes == ("1 of the reference's 4 photos are not among the photos (d.jpg): scored as "
                             "unregistered by every method",
                             "1 of the 4 photos have no reference pose (x.jpg): a method that registers one "
                             "scores 180 degrees for each of its pairs")
    assert read_reference(model, ["photos/a.jpg", *NAMES[1:]]).notes == ()  # a folder prefix is no difference


def test_photos_only_in_subfolders_are_one_line_with_a_reference(rendered, tmp_path, capsys):
    """An ETH3D-like layout (images/dslr/*.jpg): the reference reads, the photo folder says why, exit 2."""
    folder, _ = rendered
    nested = tmp_path / "images" / "dslr"
    nested.mkdir(parents=True)
    for photo in (folder / "images").iterdir():
        (nested / photo.name).write_bytes(photo.read_bytes())
    assert read_reference(folder, []).notes == ()
    assert main(["reconstruct", str(tmp_path / "images"), "--reference", str(folder), "--out",
                 str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err


@pytest.mark.parametrize("text", [False, True])
def test_a_model_of_poses_alone_without_points3d_is_a_reference(poses, tmp_path, text):
    model = write_colmap(tmp_path / "binary", poses)
    if text:
        (tmp_path / "text").mkdir()
        pycolmap.Reconstruction(str(model)).write_text(str(tmp_path / "text"))
        model = tmp_path / "text"
    for part in model.glob("points3D.*"):
        part.unlink()
    reference = read_reference(model, NAMES)
    assert sorted(reference.poses) == NAMES and all(np.allclose(reference.poses[n][0], poses[n][0]) for n in NAMES)


def test_a_bundler_file_of_poses_alone_is_a_reference(poses, tmp_path):
    """No point at all (a converted or hand-made reference): a camera is posed
    by its own block, not by the points seen in it."""
    path = write_bundler(tmp_path / "bundle.out", [poses["a.jpg"], None, poses["c.jpg"], poses["d.jpg"]], point=False)
    reference = read_reference(path, photo_names=NAMES)
    assert sorted(reference.poses) == ["a.jpg", "c.jpg", "d.jpg"] and reference.unposed == ("b.jpg",)
    assert all(np.allclose(reference.poses[n][1], poses[n][1]) for n in ["a.jpg", "c.jpg", "d.jpg"])
