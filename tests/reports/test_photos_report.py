"""The photos section of a report (``pipeline=photos``): its table, figure and
findings from runs shaped as the photos pipeline logs them."""
import numpy as np
import pandas as pd
import pytest

from mpe3d.reports import paper, photos

METHODS = ("bundle", "colmap", "colmap_global", "my_sfm")  # my_sfm: an SfM plug-in
# AUC@3 per (data set, method, seed); AUC@k is AUC@3 + (k - 3)
FOUNTAIN = {"bundle": 80.0, "colmap": 80.5, "colmap_global": 82.0, "my_sfm": 40.0}
CHAIR = {(8, "bundle"): (60.0, 70.0), (8, "colmap"): (64.0, 66.0), (8, "colmap_global"): (50.0, 52.0),
         (8, "my_sfm"): (10.0, 20.0), (16, "bundle"): (90.0, 92.0), (16, "colmap"): (85.0, 89.0),
         (16, "colmap_global"): (88.0, 88.0), (16, "my_sfm"): (30.0, None)}  # None: the FAILED run
SOLVE_S = {"bundle": 2.0, "colmap": 1.0, "colmap_global": 3.0, "my_sfm": 0.5}


def _run(dataset, solver, seed, auc3, *, count=250, photos_count=11, registered=11):
    row = {"status": "FINISHED" if auc3 is not None or dataset == "herzjesu" else "FAILED",
           "config_hash": f"{dataset}-{count}-{solver}-{seed}", "code": "0.1.0/aaaa", "error": "",
           "pipeline": "photos", "photos.set": dataset, "photos.solver": solver,
           "shape": "chair", "images.count": count, "images.size": 400, "seed": seed,
           "solver.name": "refine", "method": solver}
    if row["status"] == "FAILED":
        return {**row, "error": "my_sfm: no model"}
    reference = auc3 is not None
    row.update({f"pose_auc{t}": auc3 + (t - 3) if reference else np.nan for t in (1, 3, 5, 10)})
    row.update({"registered": registered, "photos": photos_count if reference else np.nan,
                "registered_fraction": registered / photos_count, "centre_error": 0.5 + seed,
                "rms_px": 0.8, "points_placed": 1000 + 10 * seed, "extract_s": 4.0, "match_s": 1.0,
                "solve_s": SOLVE_S[solver], "features_cached": float(solver != "bundle")})
    return row


def photo_runs(fountain=FOUNTAIN):
    rows = [_run("fountain-P11", m, 0, fountain[m]) for m in METHODS]
    rows += [_run("herzjesu", m, 0, None, registered=8) for m in METHODS]  # no reference poses
    for (count, method), values in CHAIR.items():
        rows += [_run("rendered", method, seed, auc, count=count, photos_count=count, registered=count)
                 for seed, auc in enumerate(values)]
    return pd.DataFrame(rows)


def test_the_table_holds_the_medians_in_order():
    table = photos.table(photo_runs())
    labels = ["ours (bundle adjustment)", "COLMAP incremental", "COLMAP global", "my_sfm"]
    assert list(table["data set"]) == [d for d in ("fountain-P11", "herzjesu", "chair, 8 photos",
                                                   "chair, 16 photos") for _ in labels]
    assert list(table["method"]) == labels * 4
    chair8 = table[table["data set"] == "chair, 8 photos"].set_index("method")
    assert chair8.loc["ours (bundle adjustment)", "AUC@3"] == 65.0  # median of 60 and 70
    assert chair8.loc["COLMAP incremental", "AUC@10"] == 65.0 + 7
    assert chair8.loc["ours (bundle adjustment)", "registered"] == "8/8"
    assert chair8.loc["ours (bundle adjustment)", "centre error (%)"] == 1.0  # seeds 0.5 and 1.5
    assert chair8.loc["ours (bundle adjustment)", "runs"] == 2
    assert chair8.loc["ours (bundle adjustment)", "points"] == "1005"
    assert chair8.loc["ours (bundle adjustment)", "features (s)"] == 5.0  # the runs that computed them
    failed = table[(table["data set"] == "chair, 16 photos") & (table["method"] == "my_sfm")].iloc[0]
    assert (failed["runs"], failed["failed"], failed["AUC@3"]) == (1, 1, 30.0)
    assert table["failed"].sum() == 1
    herz = table[table["data set"] == "herzjesu"].iloc[0]
    assert np.isnan(herz["AUC@3"]) and herz["registered"] == "8" and herz["solve (s)"] == 2.0
    assert table.set_index(["data set", "method"]).loc[("fountain-P11", "COLMAP global"), "AUC@1"] == 80.0


def test_the_findings_follow_the_numbers():
    lines = photos.findings(photo_runs())
    fountain, herz, chair8, chair16, overall = lines
    assert fountain.startswith("fountain-P11: best AUC@3: COLMAP global 82.0, next COLMAP incremental by 1.5")
    assert "ours trails COLMAP global, the better COLMAP mapper, by 2.0 points (80.0 against 82.0)" in fountain
    assert fountain.endswith("fastest of those posing photos: my_sfm (0.5 s to solve; ours (bundle adjustment) 2 s, "
                             "COLMAP incremental 1 s, COLMAP global 3 s).")
    assert herz.startswith("herzjesu: no reference poses (registered: ours (bundle adjustment) 8,")
    assert "AUC@3 a tie within 1 point: ours (bundle adjustment) 65.0, COLMAP incremental 65.0" in chair8
    assert "ours equals COLMAP incremental, the better COLMAP mapper (65.0 against 65.0)" in chair8
    assert "best AUC@3: ours (bundle adjustment) 91.0, next COLMAP global by 3.0 points" in chair16
    assert "ours leads COLMAP global, the better COLMAP mapper, by 3.0 points" in chair16
    assert overall == ("Ours within 1 point of the better COLMAP mapper's AUC@3, or ahead, on 2 of 3 data sets "
                       "(0 of 1 real folders); misses: fountain-P11 by 2.0 points.")
    better = photos.findings(photo_runs({**FOUNTAIN, "bundle": 81.7}))  # one number changed
    assert "AUC@3 a tie within 1 point: COLMAP global 82.0, ours (bundle adjustment) 81.7;" in better[0]
    assert "ours trails COLMAP global, the better COLMAP mapper, by 0.3 points" in better[0]
    assert better[-1] == ("Ours within 1 point of the better COLMAP mapper's AUC@3, or ahead, on 3 of 3 data sets "
                          "(1 of 1 real folders).")
    assert photos.ours_within(photo_runs()).verdict == "does not hold"
    assert photos.ours_within(photo_runs({**FOUNTAIN, "bundle": 81.7})).verdict == "holds"


def test_without_ours_or_a_reference_nothing_is_claimed():
    runs = photo_runs()
    runs = runs[runs["photos.solver"] != "bundle"]
    assert photos.ours_within(runs).verdict == "not enough runs"
    assert not any(line.startswith("Ours ") for line in photos.findings(runs))
    assert all("ours " not in line for line in photos.findings(runs))


@pytest.mark.parametrize("keep", ["all", "folders", "rendered"])
def test_the_report_writes_the_table_figure_and_findings(tmp_path, keep):
    runs = photo_runs()
    if keep != "all":
        runs = runs[(runs["photos.set"] == "rendered") == (keep == "rendered")]
    section = paper.Section("photos", runs, "Methods on photos.", varying=("photos.solver", "seed"),
                            code="0.1.0/aaaa")
    report = paper.write(tmp_path, [section], "photos", pdf=False)
    assert (tmp_path / "figures" / "photos_photos_auc.png").stat().st_size > 0
    assert sorted(p.name for p in (tmp_path / "tables").iterdir()) == ["photos_photos.md", "photos_photos.tex"]
    text = (tmp_path / "index.md").read_text()
    assert "Findings: which method wins where" in text and "COLMAP global" in text
    assert ("1 failed" in text) == (keep != "folders") and not report.empty
    assert "Findings" in (tmp_path / "index.html").read_text()
    tex = (tmp_path / "tables" / "photos_photos.tex").read_text()
    assert "AUC@3" in tex and "ours (bundle adjustment)" in tex


@pytest.mark.slow  # a real MLflow store (about 10 s): the full suite runs it
def test_a_photos_sweep_is_reported_from_the_tracker(tmp_path):
    """Runs of sweeps/photos.yaml logged as a sweep logs them (claimed, then
    their records), one of them failed, then ``mpe3d report --sweep``."""
    from dataclasses import replace
    from pathlib import Path

    import mpe3d.sweeps
    from mpe3d.cli import main
    from mpe3d.harness.experiment.execute import failed_record
    from mpe3d.harness.experiment.sweep import load_sweep
    from mpe3d.harness.tracking.ownership import Owner
    from mpe3d.harness.tracking.store import Tracker

    root = tmp_path / "photos"
    for name in ("fountain", "castle"):  # the runs' records are made here: the photos need not be photos
        (root / name / "images").mkdir(parents=True)
        (root / name / "images" / "a.jpg").write_text(name)
    (root / "fountain" / "sparse" / "0").mkdir(parents=True)
    (root / "fountain" / "sparse" / "0" / "images.txt").write_text("# a reference")
    path = Path(mpe3d.sweeps.__file__).parent / "photos.yaml"
    sweep = load_sweep(path, "quick", overrides=[f"photos.root={root}"])
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracker = Tracker(uri)
    experiment_id = tracker.experiment_id(sweep.name)
    parent = tracker.start_parent(experiment_id, sweep, {}, Owner.current())
    auc3 = {"bundle": 70.0, "colmap": 75.0, "colmap_global": 71.0}
    for config in sweep.runs:
        record = failed_record(config, "COLMAP made no model")
        solver, dataset = config["photos.solver"], config["photos.set"]
        if not (dataset == "castle" and solver == "colmap_global"):  # that one failed
            reference = dataset != "castle"
            metrics = {**{f"pose_auc{t}": auc3[solver] + t - 3 - config["images.count"] / 10 if reference else np.nan
                          for t in (1, 3, 5, 10)},
                       "registered": 9, "photos": 9 if reference else np.nan, "solve_s": 1.0 + len(solver),
                       "rms_px": 0.7, "points_placed": 500, "extract_s": 2.0, "match_s": 1.0,
                       "features_cached": float(solver != "bundle"), "centre_error": 0.4}
            record = replace(record, status="FINISHED", error="", metrics=metrics)
        state, run_id = tracker.claim(experiment_id, parent, config.hash(), sweep.label(config),
                                      Owner.current(), set(), record.code)
        assert state == "won"
        tracker.log_record(run_id, record, artifacts=False)
    out = tmp_path / "report"
    assert main(["report", "--sweep", str(path), "--scale", "quick", f"photos.root={root}", "--out", str(out),
                 "--tracking-uri", uri]) == 0
    table = (out / "tables" / "photos_photos.md").read_text()
    assert (out / "figures" / "photos_photos_auc.png").is_file() and not (out / "tables" / "summary.md").exists()
    lines = [line for line in table.splitlines() if line.startswith("| ") and "AUC@3" not in line]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    assert [c[:2] for c in cells] == [[d, m] for d in ("castle", "fountain", "chair, 10 photos", "chair, 25 photos")
                                      for m in ("ours (bundle adjustment)", "COLMAP incremental", "COLMAP global")]
    assert cells[2][-2:] == ["0", "1"]  # castle, COLMAP global: no finished run, one failed
    assert cells[4][3] == "50" and cells[4][6] == "9/9"  # fountain, COLMAP incremental: AUC@3 75 - 25
    text = (out / "index.md").read_text()
    assert "fountain: best AUC@3: COLMAP incremental 50.0, next COLMAP global by 4.0 points; ours trails " \
           "COLMAP incremental, the better COLMAP mapper, by 5.0 points" in text
    assert "1 failed" in text and "Findings" in (out / "index.html").read_text()
    whole = tmp_path / "whole"  # the experiment by its name renders the same way
    assert main(["report", "--experiment", "photos", "--out", str(whole), "--tracking-uri", uri]) == 0
    assert (whole / "tables" / "photos_photos.md").read_text() == table


def test_a_method_that_posed_nothing_is_not_the_fastest():
    frame = photo_runs()
    nothing = (frame["photos.set"] == "fountain-P11") & (frame["photos.solver"] == "my_sfm")
    frame.loc[nothing, "registered"] = 0
    fountain = photos.findings(frame)[0]
    assert "fastest of those posing photos: COLMAP incremental (1 s to solve" in fountain
    assert "my_sfm 0.5" not in fountain


def test_a_failed_run_of_ours_is_a_miss_and_said():
    frame = photo_runs()
    ours = (frame["photos.set"] == "fountain-P11") & (frame["photos.solver"] == "bundle")
    frame.loc[ours, "status"] = "FAILED"
    verdict = photos.ours_within(frame)
    assert verdict.verdict == photos.FAILS and "fountain-P11 (ours failed)" in verdict.numbers, verdict
    fountain = photos.findings(frame)[0]
    assert fountain.startswith("fountain-P11: failed: ours (bundle adjustment) 1 of 1 runs;"), fountain
