"""pipeline=photos: photo data sets x structure-from-motion methods, scored by pose AUC, swept and resumed."""
import re
import shutil

import numpy as np
import pytest

from mpe3d.errors import MpeError
from mpe3d.harness.experiment import execute, features
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.sweep import load_sweep
from tests.helpers import REPO, run_cli

COUNT, SIZE = 8, 300  # small, and bundle adjustment registers it whole (of 6, two pose badly for every method)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("features")


def _config(cache, **keys):
    return make_config({"pipeline": "photos", "images.count": COUNT, "images.size": SIZE,
                        "photos.cache": str(cache), **keys})


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """A folder of two data sets: rendered photos with their exact poses as a
    COLMAP model (sparse/0), and the same photos without a reference."""
    from mpe3d.harness.scene import rendering, shapes
    from mpe3d.solvers.sfm import colmap

    root = tmp_path_factory.mktemp("sets")
    cams = rendering.photo_spiral(COUNT, SIZE, 1)
    names = rendering.save_images(rendering.render(shapes.load_shape("chair"), cams, seed=1),
                                  root / "posed" / "images")
    camera = colmap.Camera("PINHOLE", SIZE, SIZE, (cams.focal, cams.focal, SIZE / 2, SIZE / 2), False, 1)
    images = [colmap.PosedImage(n, camera, R, t, np.zeros((0, 2))) for n, R, t in
              zip(names, cams.rotations, cams.translations)]
    colmap.write_model(root / "posed" / "sparse" / "0", images, np.zeros(0, dtype=np.int64), np.zeros((0, 3)), {})
    shutil.copytree(root / "posed" / "images", root / "bare" / "images")
    (root / "notes").mkdir()  # no images/: not a data set
    return root


def test_a_rendered_set_is_scored_and_its_features_shared_by_every_method(cache):
    ours = execute.run(_config(cache, **{"photos.solver": "bundle"}))
    m = ours.metrics
    assert m["registered"] == m["photos"] == COUNT and m["registered_fraction"] == 1.0
    assert m["pose_auc10"] > 80 and m["pose_auc3"] > 40  # exact photos, exact reference poses
    assert m["pose_auc1"] <= m["pose_auc3"] <= m["pose_auc5"] <= m["pose_auc10"]
    assert m["centre_error"] < 1 and m["rms_px"] < 1 and m["points_placed"] > 100
    assert m["extract_s"] > 0 and m["solve_s"] > 0
    theirs = execute.run(_config(cache, **{"photos.solver": "colmap"}))
    assert theirs.metrics["features_cached"] == 1.0  # one extraction for both methods
    assert theirs.metrics["extract_s"] == m["extract_s"]  # the cost when they were computed
    assert {"verify_s", "map_s"} <= set(theirs.metrics)
    assert theirs.metrics["registered"] >= 2


def test_features_made_by_other_code_or_another_pycolmap_are_not_reused(cache, monkeypatch, tmp_path):
    from mpe3d.harness.tracking import identity
    from mpe3d.solvers.sfm import colmap

    what = {"photos": "sha256:0", "max_features": 8192, "matching": "auto"}
    key = features.feature_key(what)
    assert features.feature_key({**what, "matching": "exhaustive"}) != key
    monkeypatch.setattr(colmap, "version", lambda: "0.0.0")
    assert features.feature_key(what) != key
    monkeypatch.undo()
    real = identity.source_fingerprint
    monkeypatch.setattr(identity, "source_fingerprint",
                        lambda text: real(text + "\nCHANGED = 1") if "def extract_and_match" in text else real(text))
    assert features.feature_key(what) != key


def test_a_damaged_cache_entry_is_made_again(tmp_path):
    calls = []

    def make(work):
        calls.append(work)
        (work / features.DATABASE).write_bytes(b"db")
        return ["a.png", "b.png"], {"extract_s": 1.0, "match_s": 0.5}, []

    first = features.features(tmp_path, "k", make)
    assert not first.cached and first.names == ["a.png", "b.png"]
    again = features.features(tmp_path, "k", make)
    assert again.cached and again.seconds["extract_s"] == 1.0 and len(calls) == 1
    (tmp_path / "k" / features.META).write_text("{not json")
    remade = features.features(tmp_path, "k", make)
    assert not remade.cached and len(calls) == 2
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # no half entry left


def test_a_folder_set_is_identified_by_its_content_not_its_place(root, tmp_path):
    config = make_config({"pipeline": "photos", "photos.root": str(root), "photos.set": "posed"})
    shutil.copytree(root / "posed", tmp_path / "elsewhere")
    moved = make_config({"pipeline": "photos", "photos.root": str(tmp_path), "photos.set": "elsewhere"})
    assert moved.hash() == config.hash()
    bare = make_config({"pipeline": "photos", "photos.root": str(root), "photos.set": "bare"})
    assert bare.hash() != config.hash()  # the same photos, without the reference
    # a folder's photos are not rendered: the rendering keys do not apply
    assert make_config({**config.values, "images.count": 17}).hash() == config.hash()


@pytest.mark.parametrize("keys, message", [
    ({"photos.set": "all", "photos.root": "ROOT"}, "photos.set=all names every data set"),
    ({"photos.set": "nowhere", "photos.root": "ROOT"}, "holds no images/ folder (it has: bare, posed)"),
    ({"photos.set": "posed"}, "needs photos.root=DIR"),
    ({"photos.solver": "nosuch"}, "photos.solver: unknown SfM method 'nosuch'"),
])
def test_a_run_that_cannot_be_is_one_line(root, tmp_path, keys, message):
    args = [f"{k}={str(v).replace('ROOT', str(root))}" for k, v in keys.items()]
    done = run_cli("run", "pipeline=photos", *args, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_the_sweep_makes_one_run_per_data_set_and_method(root):
    sweep = load_sweep(REPO / "sweeps" / "photos.yaml", "quick", overrides=[f"photos.root={root}"])
    folders = [c for c in sweep.runs if c["photos.set"] != "rendered"]
    assert sorted({c["photos.set"] for c in folders}) == ["bare", "posed"]
    assert len(folders) == 2 * 3  # the rendering axes collapse on a folder's runs
    assert {c["photos.solver"] for c in sweep.runs} == {"bundle", "colmap", "colmap_global"}
    label = sweep.label(folders[0])
    assert "images.count" not in label and "photos.set=" in label
    alone = load_sweep(REPO / "sweeps" / "photos.yaml", "quick")  # no photos.root: the rendered sets
    assert {c["photos.set"] for c in alone.runs} == {"rendered"}


@pytest.mark.slow
def test_swept_resumed_and_reported_with_a_plug_in_on_the_axis(root, cache, tmp_path):
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    args = ["sweeps/photos.yaml", f"photos.root={root}", f"photos.cache={cache}", "grid.photos.set=[all]",
            "grid.photos.solver=[colmap]", "--plugin", "examples/sfm_plugin.py",
            "--solver", "pinhole_bundle"]
    env = {"MLFLOW_TRACKING_URI": store}
    first = run_cli("sweep", *args, "--scale", "quick", "--jobs", "2", cwd=REPO, env=env)
    assert first.returncode == 0, first.stderr
    again = run_cli("sweep", *args, "--scale", "quick", "--jobs", "2", cwd=REPO, env=env)
    assert again.returncode == 0 and "nothing to run: all 4 runs are already tracked" in again.stdout
    report = run_cli("report", "--sweep", *args, "--scale", "quick", "--out", str(tmp_path / "report"),
                     cwd=REPO, env=env)
    assert report.returncode == 0, report.stderr
    text = (tmp_path / "report" / "index.md").read_text()
    assert "pinhole_bundle" in text and "posed" in text and "AUC@3" in text
    from mpe3d.harness.tracking.store import Tracker
    from mpe3d.reports.load import runs

    frame = runs(Tracker(store), "photos")
    assert len(frame) == 2 * 2 and set(frame["status"]) == {"FINISHED"}
    posed = frame[frame["photos.set"] == "posed"]
    assert posed["pose_auc3"].notna().all() and frame[frame["photos.set"] == "bare"]["pose_auc3"].isna().all()
    assert sorted(frame["photos.solver"].unique()) == ["colmap", "pinhole_bundle"]


def test_a_missing_root_in_a_sweep_is_located(tmp_path):
    with pytest.raises(MpeError, match="photos.root: .*nowhere: no such folder"):
        load_sweep(REPO / "sweeps" / "photos.yaml", "quick", overrides=[f"photos.root={tmp_path / 'nowhere'}"])


def test_two_folders_of_the_same_data_are_one_line_not_one_set_lost(root, tmp_path):
    shutil.copytree(root / "posed", tmp_path / "one")
    shutil.copytree(root / "posed", tmp_path / "two")
    with pytest.raises(MpeError, match="two and one hold the same photos and reference; keep one"):
        load_sweep(REPO / "sweeps" / "photos.yaml", "quick", overrides=[f"photos.root={tmp_path}"])


def test_a_plug_ins_lists_are_arrays_by_the_time_they_are_scored():
    from mpe3d.harness.experiment.photos_pipeline import pinhole_rms
    from mpe3d.solvers.sfm import methods

    views = [methods.SfmView(n, np.arange(3), np.array([[10.0, 10.0], [20.0, 10.0], [10.0, 20.0]]), (40, 40),
                             None, 0) for n in ("a", "b")]

    @methods.register_sfm("listy_test_method")
    def listy(given, *, random_state):
        pose = methods.SfmPose([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [0, 0, 0], 10, (10, 10))
        return methods.SfmResult({"a": pose, "b": pose}, [0, 1, 2], [[0, 0, 1], [1, 0, 1], [0, 1, 1]])

    try:
        result = methods.run_sfm("listy_test_method", views, 0)
        assert result.point_ids.dtype == np.int64 and result.poses["a"].rotation.shape == (3, 3)
        assert pinhole_rms(result, views) == pytest.approx(0.0)  # each point projects onto its keypoint
    finally:
        methods.SFM_METHODS.pop("listy_test_method", None)


@pytest.mark.parametrize("layout, message", [
    ("one set", "holds no data set (it is a data set itself: give its parent)"),
    ("empty", "holds no data set (each data set is a subfolder holding images/)"),
    ("rendered", "a data set may not be named 'rendered'"),
])
def test_a_root_that_gives_no_data_set_is_one_line(root, tmp_path, layout, message):
    where = {"one set": tmp_path / "posed", "empty": tmp_path, "rendered": tmp_path}[layout]
    if layout == "one set":
        shutil.copytree(root / "posed", where)
    if layout == "rendered":
        shutil.copytree(root / "posed", tmp_path / "rendered")
    with pytest.raises(MpeError, match=f"photos.root: .*{re.escape(message)}.* at the command line"):
        load_sweep(REPO / "sweeps" / "photos.yaml", "quick", overrides=[f"photos.root={where}"])
