"""Sweeps end to end: real joblib workers, a real SQLite MLflow store, a real
``mlflow server`` and a real dask cluster on 127.0.0.1."""
import contextlib
import io
import json
import os
import signal
import socket
import subprocess
import time
import urllib.request

import numpy as np
import pandas as pd
import psutil
import pytest
from mlflow.tracking import MlflowClient

from mpe3d.cli import main
from mpe3d.harness.experiment.execute import shaping_params
from mpe3d.harness.experiment.result import METRIC_KEYS
from mpe3d.harness.experiment.sweep import load_sweep
from mpe3d.harness.tracking.results import CONFIG_TAG
from mpe3d.harness.tracking.store import CHART_STEPS, chart_steps
from tests.helpers import free_port, run_cli, stop, wait_for

SWEEP = """
name: tiny
description: an 8-run test sweep
base:
  shape: torus
  points: 64
  visibility: {mode: exact, k: 2}
  solver: {name: sgd, max_iter: 15}
grid:
  projections: [fixed, variable]
  views: [3, 4]
repeats: 2
"""


def cli(capsys, *args):
    """``mpe3d`` in this process (cheaper than a subprocess where that is not the point)."""
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def children(client, experiment):
    exp = client.get_experiment_by_name(experiment)
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    kids = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    return kids, parents


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """The 8-run sweep, run once with two workers into a fresh SQLite store."""
    folder = tmp_path_factory.mktemp("sweep")
    path = folder / "tiny.yaml"
    path.write_text(SWEEP)
    out = run_cli("sweep", str(path), "--jobs", "2", cwd=folder)
    return folder, path, out


def test_sweep_logs_every_run_finished(tracked):
    folder, path, out = tracked
    assert out.returncode == 0, out.stderr
    assert (folder / "mlflow.db").is_file()  # the default store, in the working directory
    client = MlflowClient(f"sqlite:///{folder}/mlflow.db")
    kids, parents = children(client, "tiny")
    assert len(kids) == 8 and {r.info.status for r in kids} == {"FINISHED"}
    (parent,) = parents
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["mpe3d.sweep_file"] == str(path)
    assert len(parent.data.tags["mpe3d.sweep_sha256"]) == 64
    assert {"mpe3d.version", "mpe3d.host"} <= set(parent.data.tags)
    assert parent.data.metrics["runs_finished"] == 8
    expected = {c.hash(): c for c in load_sweep(path).runs}
    assert {r.data.tags["mpe3d.config_hash"] for r in kids} == set(expected)
    # the sweep's description on the experiment's page; one data set for all its runs
    assert client.get_experiment_by_name("tiny").tags["mlflow.note.content"] == "an 8-run test sweep"
    assert len({r.inputs.dataset_inputs[0].dataset.digest for r in kids}) == 1
    for run in kids:
        config = expected[run.data.tags["mpe3d.config_hash"]]
        assert run.data.tags["mlflow.parentRunId"] == parent.info.run_id
        # the keys that shaped a points run are its params, none left at None;
        # every key is in its config tag, which the reports read
        assert run.data.params == {k: str(v) for k, v in shaping_params(config).items()}
        assert not any(k.startswith(("tracks.", "images.")) for k in run.data.params)
        assert "visibility.count" not in run.data.params  # None
        assert json.loads(run.data.tags[CONFIG_TAG]) == {k: str(v) for k, v in config.flat().items()}
        (used,) = run.inputs.dataset_inputs  # the data it read, as MLflow names a data set
        assert used.dataset.name == "torus"
        assert json.loads(used.dataset.source) == {"tags": {"mpe3d.shape": "torus"}}
        assert json.loads(used.dataset.profile) == {"points": 64, "sampling": "area-uniform"}
        assert set(METRIC_KEYS) <= set(run.data.metrics)
        assert 0 <= run.data.metrics["roa"] and run.data.metrics["iterations"] <= 15
        history = client.get_metric_history(run.info.run_id, "stress_history")
        assert len(history) == run.data.metrics["iterations"] + 1  # short: every step charted
        assert min(m.value for m in history) == pytest.approx(run.data.metrics["stress"])
        files = {a.path for a in client.list_artifacts(run.info.run_id)}
        assert files == {"reconstruction.ply", "ground_truth.ply", "comparison.png"} | (
            {"stress_history.csv"} if run.data.metrics["iterations"] else set())
        if run.data.metrics["iterations"]:
            local = client.download_artifacts(run.info.run_id, "stress_history.csv")
            logged = sorted(history, key=lambda m: m.step)
            assert np.array_equal(np.loadtxt(local), [m.value for m in logged])


def test_runs_start_longest_first(tracked):
    """The 4-view runs are claimed before the 3-view ones (the sweep lists them
    mixed), so that the last runs to finish are short ones."""
    folder, _, _ = tracked
    kids, _ = children(MlflowClient(f"sqlite:///{folder}/mlflow.db"), "tiny")
    views = [int(r.data.params["views"]) for r in sorted(kids, key=lambda r: r.info.start_time)]
    assert views == sorted(views, reverse=True) and len(set(views)) == 2


def test_a_long_stress_history_is_charted_at_log_spaced_steps():
    """MLflow's chart gets at most CHART_STEPS steps (the whole history goes
    to stress_history.csv): the first and last always, dense at the start."""
    for n in (1, 2, 64, 65, 301, 5000):
        steps = chart_steps(n)
        assert len(steps) <= min(n, CHART_STEPS) and steps[0] == 0 and steps[-1] == n - 1
        assert np.all(np.diff(steps) > 0)
        assert n > CHART_STEPS or np.array_equal(steps, np.arange(n))
    assert set(range(10)) <= set(chart_steps(301))


def test_rerun_starts_nothing_and_says_so(tracked, capsys):
    folder, path, _ = tracked
    code, out, err = cli(capsys, "sweep", path, "--tracking-uri", f"sqlite:///{folder}/mlflow.db")
    assert code == 0, err
    assert "nothing to run" in out and "8 finished" in out
    client = MlflowClient(f"sqlite:///{folder}/mlflow.db")
    kids, parents = children(client, "tiny")
    assert len(kids) == 8 and len(parents) == 1


def test_runs_table_prints_numbers_from_the_store(tracked, capsys, monkeypatch):
    folder, _, _ = tracked
    client = MlflowClient(f"sqlite:///{folder}/mlflow.db")
    kids, _ = children(client, "tiny")
    monkeypatch.chdir(folder)  # the default store, ./mlflow.db
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    code, out, err = cli(capsys, "runs", "tiny", "--format", "csv")
    assert code == 0, err
    table = pd.read_csv(io.StringIO(out))
    assert len(table) == 8 and {"views", "projections", "seed", "cd_x100", "roa", "runtime_s",
                                 "code"} == set(table.columns) - {"status", "emd_x100"}
    code, out, err = cli(capsys, "runs", "tiny", "--all-columns", "--format", "json")
    every = pd.DataFrame(json.loads(out))
    assert len(every) == 8 and {"points", "cd", "stress", "config_hash", "run_id"} <= set(every.columns)
    by_hash = {r.data.tags["mpe3d.config_hash"]: r.data.metrics for r in kids}
    for _, row in every.iterrows():
        assert row["cd"] == pytest.approx(by_hash[row["config_hash"]]["cd"], rel=1e-12)
        assert row["cd_x100"] == table.set_index(["views", "projections", "seed"]).loc[
            (row["views"], row["projections"], row["seed"]), "cd_x100"]
    code, out, _ = cli(capsys, "runs", "tiny")
    assert code == 0 and out.count("FINISHED") == 8 and out.split()[:2] == ["status", "views"]
    code, out, _ = cli(capsys, "runs", "tiny", "--format", "md")
    assert code == 0 and out.count("| FINISHED") == 8
    code, _, err = cli(capsys, "runs", "tnyi")
    assert code == 2 and "no experiment 'tnyi'" in err and "did you mean 'tiny'" in err
    code, _, err = cli(capsys, "runs", "tiny", "--tracking-uri", f"sqlite:///{folder}/none.db")
    assert code == 2 and "no tracking store at" in err
    from tests.helpers import mpe3d_command
    piped = subprocess.run(f"{' '.join(mpe3d_command())} runs tiny | head -1", shell=True,
                           cwd=folder, capture_output=True, text=True, timeout=120)
    assert piped.stdout.split()[0] == "status" and "Traceback" not in piped.stderr


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_raising_run_is_failed_and_the_others_finish(tmp_path, capsys):
    (tmp_path / "broken.ply").write_bytes(b"not a mesh")
    path = tmp_path / "fail.yaml"
    path.write_text("name: failing\nbase: {points: 64, views: 3, solver: baseline}\n"
                    f"grid:\n  shape: [torus, {tmp_path / 'broken.ply'}, box]\n")
    uri = f"sqlite:///{tmp_path}/t.db"
    out = run_cli("sweep", str(path), "--jobs", "2", "--tracking-uri", uri)
    assert out.returncode == 1  # some run failed; the sweep itself went through
    assert "2 finished, 1 failed" in out.stdout and "cannot read" in out.stderr
    client = MlflowClient(uri)
    kids, _ = children(client, "failing")
    status = {r.data.params["shape"]: r for r in kids}
    assert {s: r.info.status for s, r in status.items()} == {
        "torus": "FINISHED", "box": "FINISHED", str(tmp_path / "broken.ply"): "FAILED"}
    failed = status[str(tmp_path / "broken.ply")]
    assert "cannot read" in failed.data.tags["mpe3d.error"]
    assert {a.path for a in client.list_artifacts(failed.info.run_id)} == {"error.txt"}
    # A failed run is not retried by default, only with --rerun-failed.
    code, out, _ = cli(capsys, "sweep", path, "--tracking-uri", uri)
    assert code == 0 and "--rerun-failed retries them" in out
    code, out, _ = cli(capsys, "sweep", path, "--tracking-uri", uri, "--rerun-failed",
                       "--jobs", "1", "--no-artifacts")
    assert code == 1 and "0 finished, 1 failed, 2 skipped" in out
    assert len(children(client, "failing")[0]) == 4


def test_force_reruns_everything(tmp_path, capsys):
    path = tmp_path / "two.yaml"
    path.write_text("name: two\nbase: {shape: torus, points: 64, solver: baseline}\n"
                    "grid: {views: [3, 4]}\n")
    uri = f"sqlite:///{tmp_path}/t.db"
    assert cli(capsys, "sweep", path, "--jobs", "1", "--tracking-uri", uri)[0] == 0
    code, out, _ = cli(capsys, "sweep", path, "--jobs", "1", "--tracking-uri", uri, "--force")
    assert code == 0 and "2 finished" in out
    assert len(children(MlflowClient(uri), "two")[0]) == 4
    _, history, _ = cli(capsys, "runs", "two", "--tracking-uri", uri, "--history", "--format", "csv")
    assert len(pd.read_csv(io.StringIO(history))) == 4
    _, latest, _ = cli(capsys, "runs", "two", "--tracking-uri", uri, "--format", "csv")
    assert len(pd.read_csv(io.StringIO(latest))) == 2


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_ui_serves_the_store_on_localhost(tmp_path, capsys):
    path = tmp_path / "two.yaml"
    path.write_text("name: two\ndescription: a torus seen twice\n"
                    "base: {shape: torus, points: 64, solver: baseline}\n")
    assert cli(capsys, "sweep", path, "--jobs", "1", "--tracking-uri",
               f"sqlite:///{tmp_path}/mlflow.db")[0] == 0
    port = free_port()
    from tests.helpers import mpe3d_command
    # As a user starts it: in our process group, so only `kill PID` can stop it cleanly.
    ui = subprocess.Popen([*mpe3d_command(), "ui", "--port", str(port)], cwd=tmp_path,
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        wait_for(f"http://127.0.0.1:{port}/health", ui)
        base = f"http://127.0.0.1:{port}"
        with urllib.request.urlopen(f"{base}/api/2.0/mlflow/experiments/get-by-name?"
                                    "experiment_name=two", timeout=10) as answer:
            experiment = json.loads(answer.read())["experiment"]
        # what the UI reads: the experiment's description, each run's data set and params
        assert {"key": "mlflow.note.content", "value": "a torus seen twice"} in experiment["tags"]
        query = json.dumps({"experiment_ids": [experiment["experiment_id"]],
                            "filter": "tags.`mpe3d.config_hash` != ''"}).encode()
        request = urllib.request.Request(f"{base}/api/2.0/mlflow/runs/search", data=query,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as answer:
            (run,) = json.loads(answer.read())["runs"]
        (used,) = run["inputs"]["dataset_inputs"]
        assert used["dataset"]["name"] == "torus"
        assert json.loads(used["dataset"]["source"]) == {"tags": {"mpe3d.shape": "torus"}}
        params = {p["key"] for p in run["data"]["params"]}
        assert {"shape", "points", "views", "solver.name"} <= params
        assert not any(k.startswith(("tracks.", "images.")) for k in params)
        # The picture of a child run, as the UI fetches it.
        kids, parents = children(MlflowClient(f"sqlite:///{tmp_path}/mlflow.db"), "two")
        with urllib.request.urlopen(f"{base}/get-artifact?path=comparison.png&"
                                    f"run_uuid={kids[0].info.run_id}", timeout=10) as answer:
            assert answer.read(8) == b"\x89PNG\r\n\x1a\n"
        with urllib.request.urlopen(f"{base}/get-artifact?path=summary/index.html&"
                                    f"run_uuid={parents[0].info.run_id}", timeout=10) as answer:
            assert b"<table" in answer.read()
        server = psutil.Process(ui.pid).children(recursive=True)
        assert server, "the UI started no server"
    finally:
        ui.send_signal(signal.SIGTERM)  # `kill PID`
        try:
            ui.wait(timeout=30)
        except subprocess.TimeoutExpired:
            stop(ui)
    assert "serving the store sqlite:///" in ui.stdout.read()
    gone, alive = psutil.wait_procs(server, timeout=15)
    assert not alive, f"left behind: {[p.pid for p in alive]}"
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    try:
        code, _, err = cli(capsys, "ui", "--port", busy.getsockname()[1])
        assert code == 2 and "is in use" in err
    finally:
        busy.close()
    code, _, err = cli(capsys, "ui", "--tracking-uri", "http://127.0.0.1:1")
    assert code == 2 and "open it in a browser" in err


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_killed_sweep_keeps_its_runs_and_resumes(tmp_path):
    path = tmp_path / "slow.yaml"
    # about 2 s a run, so that runs are left to kill (300 iterations were 0.2 s a run)
    path.write_text("name: slow\nbase: {shape: torus, points: 200, views: 4,\n"
                    "       solver: {name: sgd, max_iter: 20000, tol: 0.0}}\nrepeats: 4\n")
    uri = f"sqlite:///{tmp_path}/t.db"
    from tests.helpers import mpe3d_command, new_store

    new_store(uri)  # polled below while the sweep runs
    sweep = subprocess.Popen([*mpe3d_command(), "sweep", str(path), "--jobs", "1",
                              "--tracking-uri", uri, "--no-artifacts"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    finished = []
    while not finished and time.time() < deadline:  # kill it once a run is logged
        time.sleep(0.5)
        assert sweep.poll() is None, sweep.communicate()
        if MlflowClient(uri).get_experiment_by_name("slow") is not None:
            finished = [r for r in children(MlflowClient(uri), "slow")[0]
                        if r.info.status == "FINISHED"]
    sweep.terminate()
    _, err = sweep.communicate(timeout=60)
    assert sweep.returncode == 130 and "run the same command to resume" in err
    kids, (parent,) = children(MlflowClient(uri), "slow")
    assert parent.info.status == "KILLED"
    done = {r.data.tags["mpe3d.config_hash"] for r in kids if r.info.status == "FINISHED"}
    assert 1 <= len(done) < 4
    assert {r.info.status for r in kids} <= {"FINISHED", "KILLED"}  # nothing left RUNNING
    resumed = run_cli("sweep", str(path), "--jobs", "2", "--tracking-uri", uri, "--no-artifacts")
    assert resumed.returncode == 0, resumed.stderr
    assert f"{4 - len(done)} finished, 0 failed, {len(done)} skipped" in resumed.stdout
    kids, _ = children(MlflowClient(uri), "slow")
    assert len({r.data.tags["mpe3d.config_hash"] for r in kids if r.info.status == "FINISHED"}) == 4


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_sweep_on_an_existing_dask_scheduler(tmp_path):
    import logging

    from distributed import Client, LocalCluster

    path = tmp_path / "two.yaml"
    path.write_text("name: two\nbase: {shape: torus, points: 64, solver: baseline}\n"
                    "grid: {views: [3, 4]}\n")
    uri = f"sqlite:///{tmp_path}/t.db"
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        out = run_cli("sweep", str(path), "--scheduler", cluster.scheduler_address,
                      "--tracking-uri", uri, "--no-artifacts")
        with Client(cluster) as client:
            worker_pids = set(client.run(os.getpid).values())
    assert out.returncode == 0, out.stderr
    kids, _ = children(MlflowClient(uri), "two")
    assert len(kids) == 2 and {r.info.status for r in kids} == {"FINISHED"}
    ran_on = {int(r.data.tags["mpe3d.worker"].rsplit(":", 1)[1]) for r in kids}
    assert ran_on <= worker_pids  # the cluster's workers did the work, not the CLI


def test_a_failed_store_opening_leaves_no_litter(tmp_path, capsys, monkeypatch):
    path = tmp_path / "s.yaml"
    path.write_text("name: s\nbase: {shape: torus, points: 48, solver: baseline}\n")
    (tmp_path / "notadb.db").write_text("these are my notes, not a database\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(["sweep", str(path), "--quiet", "--tracking-uri", f"sqlite:///{tmp_path}/notadb.db"])
    err = capsys.readouterr().err
    assert code == 3 and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no notadb.db.lock
    assert (tmp_path / "notadb.db").read_text().startswith("these are my notes")
    # A store that fails after its folders and file were made takes them away again.
    from mlflow.tracking import MlflowClient

    from mpe3d.errors import StoreError
    from mpe3d.harness.tracking.store import Tracker

    def refuse(self, *args, **kwargs):
        raise RuntimeError("the disk said no")
    monkeypatch.setattr(MlflowClient, "search_experiments", refuse)
    with pytest.raises(StoreError, match="the disk said no"):
        Tracker(f"sqlite:///{tmp_path}/new/deeper/t.db")
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def _store_contents(database):
    """A SQLite store's schema, its journal mode and every row but the times.
    Each statement's lines are sorted: MLflow's own migrations write a table's
    constraints in an order that varies from one store to the next."""
    import sqlite3

    with contextlib.closing(sqlite3.connect(database)) as connection:
        schema = [(kind, name, sorted(line.strip(" ,") for line in (sql or "").splitlines()))
                  for kind, name, sql in connection.execute(
                      "SELECT type, name, sql FROM sqlite_master ORDER BY name")]
        rows = {table: connection.execute(f"SELECT * FROM {table}").fetchall()
                for kind, table, _ in schema if kind == "table"}
        mode = connection.execute("PRAGMA journal_mode").fetchone()
    rows["experiments"] = [row[:4] + row[6:] for row in rows["experiments"]]  # not its two times
    return schema, rows, mode


def test_a_new_store_is_a_copy_of_the_one_mlflow_makes_and_a_bad_template_is_made_again(tmp_path, monkeypatch):
    from mpe3d.harness.tracking.store import Tracker, store_template

    monkeypatch.chdir(tmp_path)  # MLflow's Default experiment keeps its artifacts under ./mlruns
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "a-file"))  # no cache folder can be made there
    assert store_template() is None
    Tracker(f"sqlite:///{tmp_path}/own/mlflow.db")  # MLflow runs its migrations
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    template = store_template()  # made where MLflow would put its Default experiment elsewhere
    assert template.parent == tmp_path / "cache" / "mpe3d"
    monkeypatch.chdir(tmp_path)
    Tracker(f"sqlite:///{tmp_path}/copy/mlflow.db")
    own = _store_contents(tmp_path / "own" / "mlflow.db")
    assert own[1]["experiments"] and own[2] == ("wal",)  # MLflow's Default experiment; WAL
    assert _store_contents(tmp_path / "copy" / "mlflow.db") == own
    assert _store_contents(template)[1]["experiments"] == []  # MLflow adds it for each copy
    template.write_bytes(b"not a store")  # damaged: refused, MLflow makes the store, then a new template
    Tracker(f"sqlite:///{tmp_path}/after/mlflow.db")
    assert _store_contents(tmp_path / "after" / "mlflow.db") == own
    assert not template.exists()
    assert _store_contents(store_template()) == _store_contents(tmp_path / "cache" / "mpe3d" / template.name)
    Tracker(f"sqlite:///{tmp_path}/again/mlflow.db")
    assert _store_contents(tmp_path / "again" / "mlflow.db") == own


def test_runs_of_the_papers_full_sweeps_fit_a_120_column_terminal(monkeypatch):
    """Every config of each paper sweep at full scale, with metrics as wide as
    they print (an exact solver's 1e-14, a slow run's seconds), and a failure."""
    from mpe3d.harness.experiment.sweep import load_sweep
    from mpe3d.reports.runs_table import format_runs, runs_table
    from mpe3d.sweeps import paper_sweeps

    monkeypatch.setenv("COLUMNS", "120")
    rng = np.random.default_rng(0)
    for path in paper_sweeps():
        sweep = load_sweep(path)
        frame = pd.DataFrame([c.flat() for c in sweep.runs])
        n = len(frame)
        frame = frame.assign(status="FINISHED", config_hash=[c.hash() for c in sweep.runs],
                             code="0.1.0/5b9ceada2ba6", error="", run_id="x",
                             start_time=pd.Timestamp("2026-12-03"),
                             cd_x100=10.0 ** rng.uniform(-15, 2, n), emd_x100=10.0 ** rng.uniform(-15, 2, n),
                             roa=10.0 ** rng.uniform(-17, 0, n), runtime_s=10.0 ** rng.uniform(-4, 3, n))
        frame.loc[0, ["status", "error"]] = ["FAILED", "MpeError: " + "a long reason " * 20]
        lines = format_runs(runs_table(frame, all_columns=False), "text").splitlines()
        assert max(map(len, lines)) <= 120, (sweep.name, lines[0])
        assert lines[-1].startswith("FAILED ") and "MpeError: a long reason" in lines[-1]
        assert len(lines) == len(frame) + 2  # the header, a row per run, the failure below


def test_a_long_config_is_kept_whole_and_a_cut_one_gives_way_to_the_params():
    """MLflow cuts a tag at 8,000 characters without an error: a config longer
    than that goes in parts and reads back whole; a tag cut short (or none, a
    run logged before the tag) reads as nothing, so the params stand in."""
    from mpe3d.harness.tracking.results import CONFIG_TAG, TAG_CHARS, config_of, config_tags

    config = {f"solver.option_{i}": "x" * 300 for i in range(60)}
    tags = config_tags(config)
    assert len(tags) > 1 and all(len(v) <= TAG_CHARS for v in tags.values())
    assert config_of(tags) == config
    assert config_of({CONFIG_TAG: tags[CONFIG_TAG]}) == {}  # its other parts lost
    assert config_of({}) == {}
