"""VGG's nview-corners data sets: read by content, their companions found by name, damage refused in one line."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mpe3d import reconstruct
from mpe3d.errors import MpeError
from mpe3d.harness.experiment import execute
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.userdata import vgg
from mpe3d.harness.userdata.formats import content_digest, read_views
from tests.helpers import SHARED, run_cli


def _write_vgg(folder, stem="house", n_points=80, n_views=5, seed=2, cameras=True, p3d=True):
    """A VGG set of pinhole views: shuffled corner files with unmatched corners
    among them, a track table with stars, the .P files and the .p3d points."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n_points, 3))
    K = np.array([[900.0, 0, 380], [0, 900.0, 290], [0, 0, 1]])
    table = np.full((n_points, n_views), -1)
    for k in range(n_views):
        R = Rotation.from_euler("y", 8.0 * k - 16, degrees=True).as_matrix()
        P = K @ np.hstack([R, [[0.2 * k], [0.0], [9.0]]])
        h = np.c_[X, np.ones(n_points)] @ P.T
        uv = h[:, :2] / h[:, 2:]
        seen = np.flatnonzero(rng.random(n_points) < 0.8)
        corners = np.vstack([uv[seen], rng.uniform(0, 700, (7, 2))])  # 7 corners no track uses
        order = rng.permutation(len(corners))
        table[seen, k] = np.argsort(order)[:len(seen)]
        prefix = f"{stem}.{k:03d}" if stem else f"{k + 1:03d}"
        np.savetxt(folder / f"{prefix}.corners", corners[order], fmt="%.12f")
        if cameras:
            np.savetxt(folder / f"{prefix}.P", P, fmt="%.15g")
    name = f"{stem}.nview-corners" if stem else "nview-corners"
    lines = [" ".join("*" if v < 0 else str(v) for v in row) for row in table]
    (folder / name).write_text("\n".join(lines) + "\n")
    if p3d:
        np.savetxt(folder / (f"{stem}.p3d" if stem else "p3d"), X, fmt="%.15g")
    return folder / name, X, table


@pytest.mark.parametrize("stem", ["house", ""])
def test_the_tracks_come_back_as_written(tmp_path, stem):
    path, X, table = _write_vgg(tmp_path, stem)
    assert vgg.sniff(path)
    views = read_views(path)
    assert len(views) == 5
    for k, view in enumerate(views):
        assert np.array_equal(view["ids"], np.flatnonzero(table[:, k] >= 0))
    truth, cameras = vgg.read_reference(path)
    assert np.allclose(truth[1], X) and list(cameras) == [view["name"] for view in views]  # by view name
    assert np.stack(list(cameras.values())).shape == (5, 3, 4)


def test_a_vgg_set_reconstructs_and_scores_against_its_own_reference(tmp_path):
    path, X, _ = _write_vgg(tmp_path)
    result = reconstruct(path, camera="perspective", principal_point=(380.0, 290.0))
    assert result.report["reprojection_rms_px"] < 1e-4
    run = execute.run(make_config({"pipeline": "tracks", "tracks.path": str(path),
                                   "tracks.camera": "perspective"}))
    assert run.metrics["error_3d_pct"] < 0.5 and "centre_error_pct" in run.metrics


def test_a_companion_file_is_part_of_the_identity(tmp_path):
    path, _, _ = _write_vgg(tmp_path)
    before = content_digest(path)
    corners = tmp_path / "house.002.corners"
    corners.write_text(corners.read_text().replace("1", "2", 1))
    assert content_digest(path) != before


def _damage(tmp_path, what):
    path, _, _ = _write_vgg(tmp_path)
    lines = path.read_text().splitlines()
    if what == "short row":
        lines[3] = " ".join(lines[3].split()[:-1])
    elif what == "bad token":
        lines[4] = lines[4].replace(lines[4].split()[0], "x7", 1)
    elif what == "corner out of range":
        lines[2] = " ".join(["999"] + lines[2].split()[1:])
    elif what == "missing corners":
        (tmp_path / "house.003.corners").unlink()
    elif what == "bad corners":
        (tmp_path / "house.001.corners").write_text("1.0 2.0\nthree 4.0\n")
    elif what == "p3d count":
        (tmp_path / "house.p3d").write_text("1 2 3\n")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("what, says", [
    ("short row", "row 4 has 4 entries, row 1 has 5"),
    ("bad token", "row 5: 'x7' is neither a corner index nor *"),
    ("corner out of range", "row 3, view 0: corner 999"),
    ("missing corners", "house.003.corners is not beside it"),
    ("bad corners", "house.001.corners: not a table of numbers"),
])
def test_damaged_sets_get_one_line(tmp_path, what, says):
    path = _damage(tmp_path, what)
    done = run_cli("reconstruct", str(path), "--out", str(tmp_path / "cloud.ply"))
    assert done.returncode == 2, done.stderr
    assert says in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "cloud.ply").exists()


def test_a_reference_that_does_not_match_the_tracks_is_refused(tmp_path):
    path = _damage(tmp_path, "p3d count")
    with pytest.raises(MpeError, match="1 points for the 80 tracks"):
        vgg.read_reference(path)


def test_a_bal_problem_is_not_taken_for_a_track_table(tmp_path):
    path = tmp_path / "problem.txt"
    path.write_text("2 3 4\n0 0 -1.5 2.25\n")
    assert not vgg.sniff(path)


@pytest.mark.skipif(not (SHARED / "realdata" / "house").is_dir(), reason="needs ../shared/realdata")
def test_house_written_as_vgg_reads_back_as_its_csv(tmp_path):
    import pandas as pd

    frame = pd.read_csv(SHARED / "realdata" / "house" / "keypoints.csv")
    views = sorted(frame["view"].unique())
    tracks = np.full((frame["point"].max() + 1, len(views)), -1)
    for k, view in enumerate(views):
        part = frame[frame["view"] == view]
        np.savetxt(tmp_path / f"house.{k:03d}.corners", part[["x", "y"]].to_numpy(), fmt="%.17g")
        tracks[part["point"].to_numpy(), k] = np.arange(len(part))
    (tmp_path / "house.nview-corners").write_text(
        "\n".join(" ".join("*" if v < 0 else str(v) for v in row) for row in tracks) + "\n")
    back = read_views(tmp_path / "house.nview-corners")
    assert sum(len(v["ids"]) for v in back) == len(frame)
