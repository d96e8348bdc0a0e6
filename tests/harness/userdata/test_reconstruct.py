"""mpe3d reconstruct: every input format round trip, every validation error, ids, atomic writes."""
import json

import numpy as np
import pandas as pd
import pytest
import trimesh

from mpe3d.cli import main
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.files import atomic_write
from mpe3d.harness.scene.metrics import roa
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams
from mpe3d.harness.userdata.formats import write_cloud
from mpe3d.harness.userdata.reconstruct import reconstruct
from tests.helpers import close_up_keypoints, run_cli


def scene(observe_as="coordinates", points=200):
    config = make_config({"shape": "chair", "points": points, "views": 5, "observe": observe_as})
    streams = seed_streams(0)
    sc = build_scene(config, streams)
    return sc, observe(sc, config, streams)[0]


def write_input(folder, fmt, obs):
    """The views of ``obs`` in one of the input formats; returns the path."""
    if fmt == "csv":
        rows = [(f"cam{k}", i, *xy) for k, v in enumerate(obs.views) for i, xy in zip(v.ids, v.coordinates)]
        path = folder / "views.csv"
        pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(path, index=False)
    elif fmt in ("npz", "npz-dist"):
        path = folder / "views.npz"
        key = "dist" if fmt == "npz-dist" else "xy"
        np.savez(path, **{f"view{k}_{name}": value for k, v in enumerate(obs.views)
                          for name, value in (("ids", v.ids), (key, _data(v, key)))})
    elif fmt == "folder":
        path = folder / "views"
        path.mkdir()
        for k, v in enumerate(obs.views):
            np.savez(path / f"view{k}.npz", ids=v.ids, xy=v.coordinates)
    else:
        key = "dist" if fmt == "json-dist" else "xy"
        path = folder / "views.json"
        path.write_text(json.dumps({"views": [{"ids": v.ids.tolist(), key: _data(v, key).tolist()}
                                              for v in obs.views]}))
    return path


def _data(view, key):
    return view.distance_matrix() if key == "dist" else view.coordinates


@pytest.mark.parametrize("fmt", ["csv", "npz", "npz-dist", "folder", "json", "json-dist"])
@pytest.mark.parametrize("setting", ["fixed", "variable"])
def test_round_trip_through_the_cli(tmp_path, fmt, setting):
    sc, obs = scene()
    source = write_input(tmp_path, fmt, obs)
    args = [str(source), "--out", str(tmp_path / "cloud.ply"), "--report", str(tmp_path / "r.json")]
    if setting == "fixed":
        np.save(tmp_path / "P.npy", sc.rotations)  # 3x3 rotations: their first two rows are P^k
        args += ["--projections", str(tmp_path / "P.npy")]
    assert main(["reconstruct", *args]) == 0
    cloud = trimesh.load(tmp_path / "cloud.ply")
    ids = cloud.metadata["_ply_raw"]["vertex"]["data"]["id"]
    assert roa(np.asarray(cloud.vertices), sc.points[ids]) < 1e-8
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["setting"] == setting and report["unplaced"]["count"] == 0
    # keypoints pose bundle adjustment (residuals in pixels), distances the stress
    residuals = "rms_residual_per_view" if "dist" in fmt else "rms_px_per_view"
    assert report["objective"] == ("stress" if "dist" in fmt else "reprojection")
    assert len(report[residuals]) == 5 and max(report[residuals]) < 1e-8
    assert np.asarray(report["projections"]).shape == (5, 2, 3) and report["runtime_s"] > 0


def test_the_installed_command_and_text_ids(tmp_path):
    sc, obs = scene()
    rows = [(k, f"kp-{i}", *xy) for k, v in enumerate(obs.views) for i, xy in zip(v.ids, v.coordinates)]
    pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(tmp_path / "kp.csv", index=False)
    done = run_cli("reconstruct", "kp.csv", "--out", "cloud.ply", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "200 points from 5 views (variable cameras, scaled camera, bundle adjustment)" \
        in done.stdout
    raw = trimesh.load(tmp_path / "cloud.ply").metadata["_ply_raw"]["vertex"]["data"]["id"]
    labels = [bytes(chars).rstrip(b"\0").decode() for chars in raw["f1"]]  # (count, bytes) pairs
    order = [int(label.split("-")[1]) for label in labels]
    assert sorted(labels) == sorted(f"kp-{i}" for i in range(200))
    assert roa(np.asarray(trimesh.load(tmp_path / "cloud.ply").vertices), sc.points[order]) < 1e-8


@pytest.mark.parametrize("suffix", [".csv", ".npy"])
def test_csv_and_npy_outputs_keep_ids(tmp_path, suffix):
    points, ids = np.random.default_rng(0).normal(size=(10, 3)), np.arange(100, 110)
    write_cloud(tmp_path / f"c{suffix}", points, ids)
    if suffix == ".csv":
        back = pd.read_csv(tmp_path / "c.csv")
        assert list(back["id"]) == list(ids) and np.allclose(back[["x", "y", "z"]], points, atol=0)
    else:
        back = np.load(tmp_path / "c.npy")
        assert list(back["id"]) == list(ids) and np.array_equal(back["x"], points[:, 0])


def test_an_interrupted_write_leaves_no_file(tmp_path):
    target = tmp_path / "cloud.ply"

    def half_then_interrupt(temp):
        temp.write_bytes(b"ply\nformat binary_little_endian 1.0\n")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, half_then_interrupt)
    assert list(tmp_path.iterdir()) == []
    target.write_text("the old cloud")
    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, half_then_interrupt)
    assert target.read_text() == "the old cloud" and len(list(tmp_path.iterdir())) == 1


CSV_ERRORS = [
    ("view,point,x\n0,1,0.5\n", "missing column 'y'"),
    ("view,point,x,y\n0,1,0.5,abc\n", "row 2: y is not a finite number ('abc')"),
    ("view,point,x,y\n0,1,0.5,nan\n", "row 2: y is not a finite number"),
    ("view,point,x,y\n0,1,0.5,inf\n", "row 2: y is not a finite number"),
    ("view,point,x,y\n0,1,0,0\n0,2,1,0\n0,1,2,2\n", "row 4: point '1' appears twice in view '0' (first at row 2)"),
    ("view,point,x,y\n0,1,0,0\n0,2,1,0\n0,3,1,1\n1,1,0,0\n1,2,1,1\n", "view '1' has 2 point(s)"),
    ("", "empty file"),
    ("view,point,x,y\n", "empty file"),
]


@pytest.mark.parametrize("text, message", CSV_ERRORS)
def test_csv_errors_are_one_line_and_write_nothing(tmp_path, capsys, text, message):
    (tmp_path / "bad.csv").write_text(text)
    assert main(["reconstruct", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.csv" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.ply").exists()


def dist_views(D0, ids0=(0, 1, 2, 3)):
    good = np.array([[0, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.5, 0, 1], [2.2, 1, 1, 0]])
    return {"views": [{"ids": list(ids0), "dist": D0}, {"ids": [0, 1, 2, 3], "dist": good.tolist()}]}


GOOD = [[0, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.5, 0, 1], [2.2, 1, 1, 0]]
JSON_ERRORS = [
    (dist_views([[0, 1, 2], [1, 0, 1], [2, 1, 0], [1, 1, 1]]), "dist is 4x3, not square"),
    (dist_views([[0, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.7, 0, 1], [2.2, 1, 1, 0]]), "dist is not symmetric (row 1, column 2"),
    (dist_views([[0, -1, 2, 2.2], [-1, 0, 1.5, 1], [2, 1.5, 0, 1], [2.2, 1, 1, 0]]), "dist has a negative entry"),
    (dist_views([[0.5, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.5, 0, 1], [2.2, 1, 1, 0]]), "dist has a non-zero diagonal (row 0"),
    (dist_views(GOOD, ids0=(0, 1, 2)), "dist is 4x4 but ids has 3 entries"),
    (dist_views([[0, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.5, 0, None], [2.2, 1, 1, 0]]), "view '0': dist row 2 is not a finite number"),
    (dist_views([[0, 1, 2, 2.2], [1, 0, 1.5, 1], [2, 1.5, 0, "far"], [2.2, 1, 1, 0]]), "view '0': dist holds a non-numeric value"),
    ({"views": [{"ids": [0, 1, 2], "xy": [[0, 0], [1, 0]]}, {"ids": [0, 1, 2], "xy": [[0, 0], [1, 0], [0, 1]]}]}, "xy is 2x2, expected 3x2"),
    ({"cams": []}, "expected an object with a list 'views'"),
]


@pytest.mark.parametrize("data, message", JSON_ERRORS)
def test_json_and_distance_errors(tmp_path, capsys, data, message):
    (tmp_path / "bad.json").write_text(json.dumps(data))
    assert main(["reconstruct", str(tmp_path / "bad.json"), "--out", str(tmp_path / "c.ply")]) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.json" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.ply").exists()


@pytest.mark.parametrize("projections, message", [
    (np.tile(np.eye(3)[:2], (4, 1, 1)), "4 matrices for 5 views"),
    (np.zeros((5, 3, 2)), "projection 0 is 3x2, expected 2x3"),
    (np.tile(np.array([[1.0, 0, 0], [0.5, 1, 0]]), (5, 1, 1)), "projection 0: rows are not orthonormal"),
])
def test_projection_file_errors(tmp_path, capsys, projections, message):
    _, obs = scene()
    source = write_input(tmp_path, "npz", obs)
    np.save(tmp_path / "P.npy", projections)
    code = main(["reconstruct", str(source), "--out", str(tmp_path / "c.ply"),
                 "--projections", str(tmp_path / "P.npy")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.ply").exists()


@pytest.mark.parametrize("name, out, message", [
    ("views.txt", "c.ply", "unknown input format '.txt'"),
    ("views.csv", "c.obj", "unknown output format '.obj'"),
    ("missing.csv", "c.ply", "missing.csv: no such file"),
    ("empty.npz", "c.ply", "empty file"),
])
def test_file_errors(tmp_path, capsys, name, out, message):
    for existing in ("views.txt", "views.csv", "empty.npz"):
        (tmp_path / existing).write_text("" if existing == "empty.npz" else "view,point,x,y\n0,1,0,0\n")
    code = main(["reconstruct", str(tmp_path / name), "--out", str(tmp_path / out)])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / out).exists()


def test_the_api_takes_lists_of_views():
    sc, obs = scene(observe_as="distances", points=120)
    views = [{"ids": v.ids, "dist": v.distances} for v in obs.views]
    result = reconstruct(views, solver="factorize")
    assert roa(result.points, sc.points[result.ids]) < 1e-8
    with pytest.raises(MpeError, match="loss=.huber. needs solver=.refine."):
        reconstruct(views, solver="factorize", loss="huber")


def test_sparse_pair_stress_gradient_matches_finite_differences():
    from mpe3d.solvers.stress import DENSE_LIMIT, Stress

    sc, obs = scene(points=int(DENSE_LIMIT * 2.2))
    stress = Stress(obs)
    assert stress.sparse and stress.n_pairs < 40 * obs.n_points  # no n x n anywhere
    rng = np.random.default_rng(1)
    X = sc.points + 1e-2 * rng.normal(size=sc.points.shape)
    P = sc.projections
    _, gX, gP = stress.value_and_grad(X, P, want_P=True)
    V, W = rng.normal(size=X.shape), rng.normal(size=P.shape)
    h = 1e-6
    numeric = (stress.value(X + h * V, P + h * W) - stress.value(X - h * V, P - h * W)) / (2 * h)
    assert numeric == pytest.approx(np.vdot(gX, V) + np.vdot(gP, W), rel=1e-6)


def test_points_seen_once_are_reported_by_id(tmp_path):
    rows = [(0, p, x, y) for p, x, y in (("a", 0, 0), ("b", 1, 0), ("c", 0, 1), ("d", 1, 1), ("lone", 2, 2))]
    rows += [(1, p, x, y) for p, x, y in (("a", 0, 0), ("b", 0.8, 0.1), ("c", 0.1, 0.9), ("d", 0.9, 1))]
    pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(tmp_path / "kp.csv", index=False)
    done = run_cli("reconstruct", "kp.csv", "--out", "c.csv", "--report", "r.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert (report["unplaced"]["count"], report["unplaced"]["ids"]) == (1, ["lone"])
    assert "mpe3d: warning: 1 points are seen in fewer than 2 views" in done.stderr
    assert "Traceback" not in done.stderr and "DegenerateWarning" not in done.stderr


def test_an_infinite_outlier_threshold_turns_refine_s_rejection_rounds_off():
    """The stress of pinhole photos misfits every row: refine's rounds reject the
    misfit's tail; ``outlier_threshold=inf`` keeps every row, as for bundle adjustment."""
    views = close_up_keypoints()
    rounds = reconstruct(views, objective="stress", solver="refine")
    kept = reconstruct(views, objective="stress", solver="refine", outlier_threshold=np.inf)
    assert rounds.report["rejected"] > 0 and kept.report["rejected"] == 0
    assert kept.report["iterations"] < rounds.report["iterations"]
