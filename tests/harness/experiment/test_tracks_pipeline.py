"""pipeline=tracks: real keypoints as experiments (perturbed, solved, scored, swept, reported)."""
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
        seen |= {note.startswith("view 'thin'") for note in out.notes}
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
    assert again.returncode == 0 and "all 18 runs are already tracked" in again.stdout
    moved = tmp_path / "moved"  # the same data elsewhere: the same runs
    for name in ("house", "dino"):
        shutil.copytree(REALDATA / name, moved / name)
    elsewhere = [f"tracks.root={moved}" if a.startswith("tracks.root=") else a for a in args]
    assert "all 18 runs are already tracked" in run_cli(*elsewhere, cwd=tmp_path).stdout
    out = tmp_path / "report"
    done = run_cli("report", "--sweep", str(REPO / "sweeps" / "realdata.yaml"), f"tracks.root={REALDATA}",
                   "tracks.views=6", "--scale", "quick", "--out", str(out), "--tracking-uri", uri, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in ("house", "dino"):
        table = (out / "tables" / f"realdata_{name}.md").read_text()
        assert "bundle (perspective)" in table and "bundle (scaled)" in table and "colmap (radial)" in table
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
def test_colmaps_mapper_is_a_method_of_the_tracks_pipeline_and_its_limits_are_checked():
    pytest.importorskip("pycolmap")
    base = {"pipeline": "tracks", "tracks.path": str(REALDATA / "house" / "keypoints.csv"),
            "tracks.truth": str(REALDATA / "house" / "gt_points.csv"), "tracks.solver": "colmap",
            "tracks.camera": "radial", "tracks.wrong_fraction": 0.03}
    result = execute.run(make_config(base))
    assert result.metrics["registered_views"] == 10 and result.metrics["error_3d_median_pct"] < 1.0
    assert result.metrics["caught"] > 0  # COLMAP's filter drops wrong matches too
    with pytest.raises(MpeError, match="tracks.camera.*tracks.solver=colmap takes"):
        make_config({**base, "tracks.camera": "scaled"})
    dino = execute.run(make_config({**base, "tracks.path": str(REALDATA / "dino" / "keypoints.csv"),
                            "tracks.truth": None, "tracks.views": 6}))
    assert dino.metrics["registered_views"] == 0 and np.isnan(dino.metrics["rms_px"])  # a result, not a crash
    assert "registered no two views" in dino.facts["warnings"][-1]
