"""pipeline=tracks: real keypoints as experiments (perturbed, solved, scored, swept, reported)."""
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from mpe3d.errors import MpeError
from mpe3d.harness.experiment import execute, tracks_pipeline
from mpe3d.harness.experiment.config import make_config
from tests.helpers import REPO, SHARED, run_cli, scaled_track_set, short_track_set

REALDATA = SHARED / "realdata"


def _config(folder, **keys):
    return make_config({"pipeline": "tracks", "tracks.root": str(folder), "tracks.path": "keypoints.csv",
                        "tracks.truth": "points.csv", "tracks.camera": "scaled", **keys})


def test_exact_keypoints_reconstruct_exactly(tmp_path):
    scaled_track_set(tmp_path)
    result = execute.run(_config(tmp_path))
    m = result.metrics
    assert m["rms_px"] < 1e-6 and m["rms_px_all"] < 1e-6 and m["rms_px_clean"] < 1e-6
    assert m["error_3d_pct"] < 1e-6 and m["error_3d_clean_median_pct"] < 1e-6
    assert m["observations"] == 300 and m["wrong"] == 0 and m["removed"] == 0
    assert m["converged"] == 1.0 and m["unplaced"] == 0
    assert len(result.scene.points) == len(result.aligned) == 60


def _views(n_views=4, n_points=40):
    rng = np.random.default_rng(0)
    return [{"name": str(k), "ids": np.arange(n_points), "xy": rng.uniform(0, 500, (n_points, 2))}
            for k in range(n_views)]


def test_perturbations_are_what_they_say_and_independent():
    views = _views()
    out = tracks_pipeline.perturb(views, 0.25, 0.1, 0.0, np.random.default_rng(7))
    assert out.removed == 40 and len(out.clean) == 120 and out.wrong.sum() == 12
    xy = np.concatenate([v["xy"] for v in out.views])
    assert np.array_equal(xy[~out.wrong], out.clean[~out.wrong])
    changed = np.flatnonzero(out.wrong)
    assert not np.any(np.all(xy[changed] == out.clean[changed], axis=1))
    offset = 0
    for view in out.views:  # a wrong match is another track's keypoint of the same view
        rows = slice(offset, offset + len(view["ids"]))
        for row in np.flatnonzero(out.wrong[rows]):
            assert any(np.array_equal(view["xy"][row], c) for c in out.clean[rows])
        offset += len(view["ids"])
    again = tracks_pipeline.perturb(views, 0.25, 0.1, 0.0, np.random.default_rng(7))
    assert np.array_equal(again.wrong, out.wrong)
    # the same draws of which observations go, whatever the share of wrong matches
    other = tracks_pipeline.perturb(views, 0.25, 0.3, 0.0, np.random.default_rng(7))
    assert [list(v["ids"]) for v in other.views] == [list(v["ids"]) for v in out.views]
    noisy = tracks_pipeline.perturb(views, 0.0, 0.0, 2.0, np.random.default_rng(7))
    moved = np.concatenate([v["xy"] for v in noisy.views]) - noisy.clean
    assert 1.7 < moved.std() < 2.3


def test_a_view_left_with_too_few_observations_is_left_out_with_a_note():
    views = _views(3) + [{"name": "thin", "ids": np.arange(3), "xy": np.zeros((3, 2)) + [1.0, 2.0]}]
    seen = set()
    for seed in range(20):
        out = tracks_pipeline.perturb(views, 0.5, 0.0, 0.0, np.random.default_rng(seed))
        thin = any(note.startswith("view 'thin'") for note in out.notes)
        assert len(out.views) == (3 if thin else 4) and ("thin" in [v["name"] for v in out.views]) != thin
        seen.add(thin)
    assert True in seen


def test_wrong_matches_are_caught_and_scored_on_the_clean_observations(tmp_path):
    scaled_track_set(tmp_path, n_points=80, n_views=6)
    clean = execute.run(_config(tmp_path)).metrics
    bad = execute.run(_config(tmp_path, **{"tracks.wrong_fraction": 0.05, "tracks.noise_px": 0.5})).metrics
    assert bad["wrong"] == 24 and bad["caught"] >= 20
    assert bad["rms_px_clean"] < 1.0 and bad["error_3d_clean_median_pct"] < 0.5
    assert clean["error_3d_clean_median_pct"] < 1e-6


def test_runs_are_identified_by_the_data_not_its_path(tmp_path):
    scaled_track_set(tmp_path / "a")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    first, moved = _config(tmp_path / "a"), _config(tmp_path / "b")
    assert first.hash() == moved.hash()
    assert first.flat()["tracks.root"] != moved.flat()["tracks.root"]
    frame = pd.read_csv(tmp_path / "b" / "keypoints.csv")
    frame.loc[0, "x"] += 1.0
    frame.to_csv(tmp_path / "b" / "keypoints.csv", index=False)
    assert _config(tmp_path / "b").hash() != first.hash()
    # the points runs' hashes do not move with the new keys
    assert make_config({}).hash() == make_config({"tracks.noise_px": 0.0}).hash()


@pytest.mark.parametrize("keys, says", [
    ({"tracks.path": None}, "tracks.path: pipeline=tracks needs"),
    ({"tracks.path": "nowhere.csv"}, "nowhere.csv: no such file"),
    ({"tracks.wrong_fraction": 1.0}, "tracks.wrong_fraction: must be in [0, 1)"),
    ({"tracks.views": 1}, "tracks.views: must be at least 2"),
    ({"tracks.objective": "stress", "tracks.loss": "cauchy"}, "tracks.loss"),
])
def test_bad_keys_are_refused_in_one_line(tmp_path, keys, says):
    scaled_track_set(tmp_path)
    with pytest.raises(MpeError) as error:
        _config(tmp_path, **keys)
    assert says in str(error.value) and "\n" not in str(error.value)


def test_the_cli_says_one_line_for_a_missing_data_set(tmp_path):
    done = run_cli("run", "pipeline=tracks", f"tracks.path={tmp_path / 'none.csv'}")
    assert done.returncode == 2
    assert "none.csv: no such file" in done.stderr and "Traceback" not in done.stderr


def test_the_stress_objective_runs_on_tracks(tmp_path):
    scaled_track_set(tmp_path)
    m = execute.run(_config(tmp_path, **{"tracks.objective": "stress", "solver.name": "refine"})).metrics
    assert m["rms_px"] < 1e-3 and m["error_3d_pct"] < 1e-3


@pytest.mark.slow
@pytest.mark.skipif(not (REALDATA / "house").is_dir(), reason="needs ../shared/realdata")
def test_the_realdata_sweep_runs_resumes_and_reports(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    args = ("sweep", str(REPO / "sweeps" / "realdata.yaml"), f"tracks.root={REALDATA}", "tracks.views=6",
            "--scale", "quick", "--jobs", "2", "--tracking-uri", uri)
    first = run_cli(*args, "--quiet", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    again = run_cli(*args, cwd=tmp_path)
    assert again.returncode == 0 and "all 24 runs are already tracked" in again.stdout
    moved = tmp_path / "moved"  # the same data elsewhere: the same runs
    for name in ("house", "dino"):
        shutil.copytree(REALDATA / name, moved / name)
    elsewhere = [f"tracks.root={moved}" if a.startswith("tracks.root=") else a for a in args]
    assert "all 24 runs are already tracked" in run_cli(*elsewhere, cwd=tmp_path).stdout
    out = tmp_path / "report"
    done = run_cli("report", "--sweep", str(REPO / "sweeps" / "realdata.yaml"), f"tracks.root={REALDATA}",
                   "tracks.views=6", "--scale", "quick", "--out", str(out), "--tracking-uri", uri, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in ("house", "dino"):
        table = (out / "tables" / f"realdata_{name}.md").read_text()
        assert "bundle (perspective)" in table and "bundle (scaled)" in table and "colmap (radial)" in table
        assert "colmap_global (radial)" in table
    assert "3D error, untouched points" in (out / "tables" / "realdata_house.md").read_text()
    assert (out / "figures" / "realdata_vs_wrong_fraction.png").stat().st_size > 10_000


def test_a_sweep_over_a_folder_that_is_not_given_names_the_key(tmp_path):
    done = run_cli("sweep", str(REPO / "sweeps" / "realdata.yaml"), "--dry-run", cwd=tmp_path)
    assert done.returncode == 2
    assert "tracks.path" in done.stderr and "realdata.yaml:" in done.stderr
    assert "tracks.root=" in done.stderr and "Traceback" not in done.stderr


def _short_track_ratios(keys, draws=5, wrong=0.05):
    clean = execute.run(make_config({**keys, "tracks.wrong_fraction": 0.0})).metrics
    bad = [execute.run(make_config({**keys, "tracks.wrong_fraction": wrong, "seed": s})).metrics
           for s in range(draws)]
    return [m["error_3d_clean_median_pct"] / clean["error_3d_clean_median_pct"] for m in bad], bad


def test_wrong_matches_in_short_tracks_leave_the_clean_points_where_they_were(tmp_path):
    """544 points in 2.6 views on average, 5% wrong matches, 5 draws: a two-view
    track's wrong match is caught by its pair, and no point runs away in depth
    (before: median 3.2x the clean error, elongation 7e4, 2 of 5 not converged)."""
    short_track_set(tmp_path)
    keys = {"pipeline": "tracks", "tracks.root": str(tmp_path), "tracks.path": "keypoints.csv",
            "tracks.truth": "points.csv", "tracks.camera": "perspective"}
    ratios, runs = _short_track_ratios(keys)
    assert np.median(ratios) <= 1.5 and max(ratios) <= 2.0
    assert all(m["converged"] == 1.0 and m["elongation"] < 100 for m in runs)


@pytest.mark.skipif(not (REALDATA / "house").is_dir(), reason="needs ../shared/realdata")
def test_house_in_five_views_with_wrong_matches_keeps_its_clean_points():
    keys = {"pipeline": "tracks", "tracks.root": str(REALDATA / "house"), "tracks.path": "keypoints.csv",
            "tracks.truth": "gt_points.csv", "tracks.camera": "perspective", "tracks.views": 5}
    ratios, runs = _short_track_ratios(keys)
    assert np.median(ratios) <= 1.5
    assert all(m["converged"] == 1.0 and m["elongation"] < 100 for m in runs)


@pytest.mark.skipif(not (REALDATA / "house").is_dir(), reason="needs ../shared/realdata")
@pytest.mark.parametrize("solver", ["colmap", "colmap_global"])
def test_colmaps_mapper_is_a_method_of_the_tracks_pipeline_and_its_limits_are_checked(solver):
    pytest.importorskip("pycolmap")
    base = {"pipeline": "tracks", "tracks.path": str(REALDATA / "house" / "keypoints.csv"),
            "tracks.truth": str(REALDATA / "house" / "gt_points.csv"), "tracks.solver": solver,
            "tracks.camera": "radial", "tracks.wrong_fraction": 0.03}
    result = execute.run(make_config(base))
    assert result.metrics["registered_views"] == 10 and result.metrics["error_3d_median_pct"] < 1.0
    assert result.metrics["caught"] > 0  # COLMAP's filter drops wrong matches too
    with pytest.raises(MpeError, match=f"^tracks.camera: tracks.solver={solver}: COLMAP has no affine camera; its "
                                       "mapper takes camera auto or radial or perspective, got scaled"):
        make_config({**base, "tracks.camera": "scaled"})
    with pytest.raises(MpeError, match=f"^tracks.loss: tracks.solver={solver}: bundle adjustment's; COLMAP's mapper "
                                       "has its own loss .a trivial one., so loss stays l2, got huber"):
        make_config({**base, "tracks.loss": "huber"})
    dino = execute.run(make_config({**base, "tracks.path": str(REALDATA / "dino" / "keypoints.csv"),
                            "tracks.truth": None, "tracks.views": 6}))
    assert dino.metrics["registered_views"] == 0 and np.isnan(dino.metrics["rms_px"])  # a result, not a crash
    assert "registered no two views" in dino.facts["warnings"][-1]


@pytest.mark.skipif(not (REALDATA / "house").is_dir(), reason="needs ../shared/realdata")
def test_colmaps_global_mapper_runs_from_the_command_line():
    pytest.importorskip("pycolmap")
    done = run_cli("run", "pipeline=tracks", f"tracks.path={REALDATA / 'house' / 'keypoints.csv'}",
                   "tracks.solver=colmap_global", "tracks.camera=radial", "--json")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["config"]["tracks"]["solver"] == "colmap_global" and result["registered_views"] == 10
    assert result["rms_px"] < 1.0


def _pinhole_track_set(folder, n_points=60, n_views=5, thin=None, scrambled=None):
    """Exact keypoints of a random cloud through pinholes of focal 1500 px turning
    12 degrees a view, written to ``folder`` as keypoints.csv (views cam0, cam1...),
    points.csv and cameras.npy (the true 3x4 cameras). View ``thin`` sees 3
    points only; view ``scrambled`` sees every point at a random pixel (no pose
    agrees with it)."""
    from mpe3d.solvers.sfm.cameras import exp_so3

    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (n_points, 3))
    K = np.array([[1500.0, 0, 960], [0, 1500.0, 640], [0, 0, 1]])
    P = np.stack([K @ np.c_[exp_so3(np.array([[0.05 * k, np.radians(12.0 * k - 24.0), 0.0]]))[0],
                            [0.1 * k, 0.0, 5.0]] for k in range(n_views)])
    rows = []
    for k in range(n_views):
        h = np.c_[X, np.ones(n_points)] @ P[k].T
        xy = h[:, :2] / h[:, 2:]
        if k == scrambled:
            xy = rng.uniform([0, 0], [1920, 1280], xy.shape)
        rows += [(f"cam{k}", i, *xy[i]) for i in range(3 if k == thin else n_points)]
    folder.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(folder / "keypoints.csv", index=False)
    pd.DataFrame({"id": range(n_points), "x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}).to_csv(
        folder / "points.csv", index=False)
    np.save(folder / "cameras.npy", P)


def _pinhole_config(folder, **keys):
    return make_config({"pipeline": "tracks", "tracks.root": str(folder), "tracks.path": "keypoints.csv",
                        "tracks.truth": "points.csv", "tracks.cameras": "cameras.npy",
                        "tracks.camera": "perspective", **keys})


def test_views_after_a_left_out_view_are_scored_against_their_own_cameras(tmp_path):
    """cam1 keeps 2 of its 3 observations (seed 1) and is left out: cam2..cam4 are
    scored against cameras 2..4 (before: against 1..3, a centre error of 28 %, where
    bundle adjustment's cameras stand about 1 % from the true ones)."""
    _pinhole_track_set(tmp_path, thin=1)
    result = execute.run(_pinhole_config(tmp_path, **{"tracks.drop_fraction": 0.2, "seed": 1}))
    m = result.metrics
    assert any(note.startswith("view 'cam1' kept") for note in result.facts["warnings"])
    assert m["views_kept"] == 4 and m["registered_views"] == 4
    assert m["centres_scored"] == 4 and m["centre_error_pct"] < 3.0


def test_reference_cameras_that_do_not_match_the_views_one_to_one_are_refused(tmp_path):
    """One matrix too many was paired with the first views without a word."""
    _pinhole_track_set(tmp_path)
    np.save(tmp_path / "cameras.npy", np.concatenate([np.load(tmp_path / "cameras.npy")] * 2)[:6])
    with pytest.raises(MpeError, match="cameras.npy: 6 cameras for the 5 views of the data set"):
        execute.run(_pinhole_config(tmp_path))
    assert "centre_error_pct" in execute.run(_pinhole_config(tmp_path, **{"tracks.views": 4})).metrics


def test_a_view_the_method_left_out_leaves_the_centre_error_of_the_others(tmp_path):
    """Bundle adjustment leaves out cam3, whose keypoints are random: the centre
    error stands over the 4 registered views (before: no centre error at all)."""
    _pinhole_track_set(tmp_path, scrambled=3)
    result = execute.run(_pinhole_config(tmp_path))
    m = result.metrics
    assert m["views_kept"] == 5 and m["registered_views"] == 4
    assert m["centres_scored"] == 4 and m["centre_error_pct"] < 3.0
    assert "centres_scored=4" in tracks_pipeline.describe(result.summary())[2]


def test_only_a_method_that_registers_nothing_finishes_without_a_cloud(tmp_path, capsys):
    """The one error a finished run may end in is ``Unregistered``: views that share
    no points are refused before any method is called, and that run FAILED for
    COLMAP's mapper as for bundle adjustment (before: COLMAP's FINISHED, with NaN
    scores, and --rerun-failed never retried it), while COLMAP on tracks it cannot
    register (60 points through scaled orthographic cameras) finishes, no view
    registered, and is not retried."""
    pytest.importorskip("pycolmap")
    from mlflow.tracking import MlflowClient

    from mpe3d.cli import main

    scaled_track_set(tmp_path / "scaled")
    frame = pd.read_csv(tmp_path / "scaled" / "keypoints.csv")
    first = frame["view"].isin(["v0", "v1"])
    (tmp_path / "split").mkdir()
    frame[(first & (frame["point"] < 30)) | (~first & (frame["point"] >= 30))].to_csv(
        tmp_path / "split" / "keypoints.csv", index=False)
    path = tmp_path / "failing.yaml"
    path.write_text(f"name: failing-tracks\nbase: {{pipeline: tracks, tracks.root: {tmp_path}}}\n"
                    "zip:\n  tracks.path: [split/keypoints.csv, split/keypoints.csv, scaled/keypoints.csv]\n"
                    "  tracks.solver: [colmap, bundle, colmap]\n  tracks.camera: [radial, perspective, radial]\n")
    uri = f"sqlite:///{tmp_path}/t.db"

    def sweep(*flags):
        code = main(["sweep", str(path), "--jobs", "1", "--no-artifacts", "--tracking-uri", uri, *flags])
        return code, capsys.readouterr().out

    code, out = sweep()
    assert code == 1 and "1 finished, 2 failed" in out
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("failing-tracks").experiment_id])
    kids = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    status = {(r.data.params["tracks.path"], r.data.params["tracks.solver"]): r for r in kids}
    assert {k: r.info.status for k, r in status.items()} == {
        ("split/keypoints.csv", "colmap"): "FAILED", ("split/keypoints.csv", "bundle"): "FAILED",
        ("scaled/keypoints.csv", "colmap"): "FINISHED"}
    for solver in ("colmap", "bundle"):
        assert "share too few points" in status["split/keypoints.csv", solver].data.tags["mpe3d.error"]
    unregistered = status["scaled/keypoints.csv", "colmap"].data
    assert unregistered.metrics["registered_views"] == 0 and np.isnan(unregistered.metrics["rms_px"])
    code, out = sweep("--rerun-failed")  # the failed runs run again; the finished one stays
    assert code == 1 and "0 finished, 2 failed, 1 skipped" in out
