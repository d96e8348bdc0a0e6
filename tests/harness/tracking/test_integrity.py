"""Results you can trust: resume at its edges, claims, zombies, outages and
determinism, with real parts (SQLite files, sweep processes killed
with SIGKILL, two sweeps started together, a real ``mlflow server`` killed
mid-sweep)."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from mpe3d.cli import main
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.execute import failed_record, run_record
from mpe3d.harness.experiment.sweep import load_sweep
from mpe3d.harness.runner import plan_sweeps
from mpe3d.harness.tracking.identity import code_identity
from mpe3d.harness.tracking.journal import Journal
from mpe3d.harness.tracking.ownership import Owner
from mpe3d.harness.tracking.store import CODE_TAG, HASH_TAG, PARENT_TAG, Tracker
from tests.helpers import children, finished_once, free_port, mpe3d_command, new_store, run_cli, stop, wait_for

# -- resume at its edges: hand-made runs in a real SQLite store ----------------------

def seed_runs(tracker, experiment, runs):
    """Runs ``(config, status, code, start_ms)`` in ``experiment``, as a sweep logs them."""
    client = tracker.client
    experiment_id = tracker.experiment_id(experiment)
    parent = client.create_run(experiment_id).info.run_id
    client.set_terminated(parent, "FINISHED")
    for config, status, code, start in runs:
        run = client.create_run(experiment_id, start_time=start, tags={
            HASH_TAG: config.hash(), PARENT_TAG: parent, **({CODE_TAG: code} if code else {})})
        client.set_terminated(run.info.run_id, status)


def sweep_file(tmp_path, name, experiment, views):
    path = tmp_path / name
    path.write_text(f"name: {experiment}\nbase: {{shape: torus, points: 48, solver: baseline}}\n"
                    f"grid: {{views: {views}}}\n")
    return load_sweep(path)


def test_resume_edges(tmp_path):
    tracker = Tracker(f"sqlite:///{tmp_path}/t.db")
    sweep = sweep_file(tmp_path, "a.yaml", "edges", [3, 4, 5, 6, 7, 8])
    c3, c4, c5, c6, c7, c8 = sweep.runs
    me, other = code_identity(), "0.0.9/000000000000"
    seed_runs(tracker, "edges", [
        (c3, "FINISHED", me, 1000), (c3, "FAILED", me, 2000),    # finished, then failed
        (c4, "FAILED", me, 1000), (c4, "FINISHED", me, 2000),    # failed, then finished
        (c5, "FAILED", me, 1000), (c5, "FAILED", me, 2000), (c5, "KILLED", me, 3000),
        (c6, "FINISHED", other, 1000), (c6, "FINISHED", None, 2000),  # only other code
        (c7, "FINISHED", other, 1000), (c7, "FAILED", me, 2000),
    ])
    (plan,) = plan_sweeps([sweep], tracker)
    assert plan.skipped_finished == 2  # c3, c4: a FINISHED run wins, whatever came after
    assert plan.skipped_failed == 2  # c5, c7: this code failed them
    assert [c.hash() for c in plan.todo] == [c6.hash(), c8.hash()] and plan.stale == 1
    (plan,) = plan_sweeps([sweep], tracker, rerun_failed=True)
    assert {c.hash() for c in plan.todo} == {c5.hash(), c6.hash(), c7.hash(), c8.hash()}
    (plan,) = plan_sweeps([sweep], tracker, reuse_stale=True)
    assert [c.hash() for c in plan.todo] == [c8.hash()] and plan.reused_stale == 1
    (plan,) = plan_sweeps([sweep], tracker, force=True)
    assert len(plan.todo) == 6 and plan.known[c3.hash()]  # a forced claim is not "done elsewhere"

    # Two sweep files sharing one experiment never plan one config twice.
    first = sweep_file(tmp_path, "b.yaml", "shared", [3, 4, 5])
    second = sweep_file(tmp_path, "c.yaml", "shared", [4, 5, 6])
    plans = plan_sweeps([first, second], tracker)
    assert [len(p.todo) for p in plans] == [3, 1] and plans[1].skipped_finished == 2

    # The reports see the best run of each config, by this code where it has one.
    frame = tracker.runs_frame("edges").set_index("config_hash")
    assert frame.loc[c3.hash(), "status"] == "FINISHED" and frame.loc[c4.hash(), "status"] == "FINISHED"
    assert frame.loc[c6.hash(), "code"] in (other, "unrecorded")
    assert frame.loc[c7.hash(), "status"] == "FINISHED" and frame.loc[c7.hash(), "code"] == other


# -- the journal --------------------------------------------------------------------

def test_journal_round_trip_and_owners(tmp_path):
    """An entry is replayed only when its writer is dead, and by one process only."""
    import psutil

    config = make_config({"shape": "torus", "points": 40, "views": 3, "solver": "baseline"})
    record = run_record(config)
    journal = Journal(tmp_path / "j")
    host = Owner.current().host
    parent = psutil.Process(os.getppid())
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True).stdout)
    owners = {"alive": Owner(host, parent.pid, round(parent.create_time(), 2)),
              "dead": Owner(host, dead, 1.0),
              "recycled": Owner(host, parent.pid, 1.0)}  # a live pid, started at another time
    for name, owner in owners.items():
        journal.write(record if name == "dead" else failed_record(config, name),
                      {"uri": "sqlite:///x.db", "owner": owner.tag()})
    journal.write(record, {"uri": "sqlite:///other.db", "owner": owners["dead"].tag()})
    assert journal.pending("sqlite:///x.db") == 3
    taken = list(journal.orphans("sqlite:///x.db"))
    assert sorted(e.record.error or "dead" for e in taken) == ["dead", "recycled"]
    for entry in taken:  # a taken entry names its new, live owner: no other sweep takes it
        assert json.loads(entry.path.read_text())["meta"]["owner"] == Owner.current().tag()
    (replayed,) = [e for e in taken if e.record.status == "FINISHED"]
    assert replayed.record.metrics == record.metrics and replayed.record.code == record.code
    np.testing.assert_array_equal(replayed.record.truth, record.truth)
    np.testing.assert_array_equal(replayed.record.stress_history, record.stress_history)
    for entry in taken:
        journal.remove(entry)
    assert journal.pending("sqlite:///x.db") == 1 and journal.pending("sqlite:///other.db") == 1


# -- real processes: kill -9, two at once, a server outage ----------------------------

# About 2 s a run (SGD's iterations, no tolerance to stop them), so that a run is
# still computing when a test kills the sweep or hangs its server. At 60
# iterations a run took 0.16 s on a faster machine, and the in-flight run
# these tests are about had sometimes been logged already.
SLOW = """
name: {name}
base: {{shape: torus, points: 200, views: 4, solver: {{name: sgd, max_iter: 20000, tol: 0.0}}}}
repeats: {repeats}
"""


def poll(predicate, seconds=120, every=0.3):
    deadline = time.time() + seconds
    while time.time() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise TimeoutError("condition not met")


def logged(uri, experiment, status="FINISHED"):
    if MlflowClient(uri).get_experiment_by_name(experiment) is None:
        return 0
    return sum(r.info.status == status for r in children(uri, experiment)[0])


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_sigkill_leaves_no_running_run_after_the_next_invocation(tmp_path):
    path = tmp_path / "k.yaml"
    path.write_text(SLOW.format(name="killed", repeats=4))
    uri = f"sqlite:///{tmp_path}/t.db"
    new_store(uri)  # polled below while the sweep runs
    sweep = subprocess.Popen([*mpe3d_command(), "sweep", str(path), "--jobs", "2", "--tracking-uri",
                              uri, "--no-artifacts", "--quiet"], cwd=tmp_path)
    poll(lambda: sweep.poll() is None and logged(uri, "killed") >= 1)
    sweep.send_signal(signal.SIGKILL)
    sweep.wait(timeout=30)
    kids, parents = children(uri, "killed")
    assert "RUNNING" in {r.info.status for r in kids + parents}  # what kill -9 leaves behind
    resumed = run_cli("sweep", str(path), "--jobs", "2", "--tracking-uri", uri, "--no-artifacts",
                      cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert "left RUNNING by sweeps that died" in resumed.stdout
    kids, parents = children(uri, "killed")
    finished_once(kids, load_sweep(path).runs)
    assert {r.info.status for r in parents} == {"KILLED", "FINISHED"}
    killed = [r for r in kids if r.info.status == "KILLED"]
    assert killed and all("died before the run ended" in r.data.tags["mpe3d.error"] for r in killed)


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_two_sweeps_started_together_compute_each_config_once(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: together\nbase: {shape: torus, points: 48, solver: baseline}\n"
                    "grid: {views: [3, 4, 5], projections: [fixed, variable]}\nrepeats: 3\n")
    uri = f"sqlite:///{tmp_path}/new.db"  # a new store: both create it at once
    command = [*mpe3d_command(), "sweep", str(path), "--jobs", "1", "--tracking-uri", uri, "--no-artifacts"]
    sweeps = [subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True) for _ in range(2)]
    outputs = [s.communicate(timeout=300) for s in sweeps]
    assert [s.returncode for s in sweeps] == [0, 0], outputs
    kids, _ = children(uri, "together")
    configs = load_sweep(path).runs
    finished_once(kids, configs)
    computed = [int(out.split(" finished,")[0].rsplit(" ", 1)[-1]) if " finished," in out else 0
                for out, _ in outputs]
    assert sum(computed) == len(configs), outputs


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_real_server_and_an_outage_that_loses_nothing(tmp_path, capsys, monkeypatch):
    """A sweep against a real ``mlflow server`` that hangs mid-sweep (SIGSTOP:
    requests time out, the hardest case) stops within 30 s (exit 3, one line),
    keeps what it computed in the journal; the server is then killed, and the
    next run, once a server is back, logs it without computing it again."""
    port = free_port()
    uri = f"http://127.0.0.1:{port}"

    def server():
        process = subprocess.Popen(
            [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
             "--workers", "1", "--backend-store-uri", f"sqlite:///{tmp_path}/server.db",
             "--artifacts-destination", str(tmp_path / "server-artifacts")],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        wait_for(uri + "/health", process)
        return process

    path = tmp_path / "o.yaml"
    path.write_text(SLOW.format(name="outage", repeats=4))
    first = server()
    try:
        sweep = subprocess.Popen([*mpe3d_command(), "sweep", str(path), "--jobs", "1", "--tracking-uri",
                                  uri, "--quiet"], cwd=tmp_path,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        poll(lambda: sweep.poll() is None and logged(uri, "outage") >= 1
             and logged(uri, "outage", "RUNNING") >= 1)  # the next run claimed: in flight
        before = logged(uri, "outage")
        os.killpg(first.pid, signal.SIGSTOP)
        hung_at = time.time()
        _, err = sweep.communicate(timeout=120)
        assert time.time() - hung_at < 30, "the sweep kept waiting for the server"
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
    assert sweep.returncode == 3 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and "wait in" in err and "mpe3d-journal" in err, err
    journaled = len(list((tmp_path / "mpe3d-journal").glob("*.json")))
    assert journaled >= 1  # the run in flight at the outage finished and was kept

    second = server()
    try:
        resumed = run_cli("sweep", str(path), "--jobs", "2", "--tracking-uri", uri, cwd=tmp_path)
        assert resumed.returncode == 0, resumed.stderr
        assert "View run" not in resumed.stdout  # MLflow's own chatter stays out of our output
        assert f"replayed {journaled} result(s)" in resumed.stdout
        configs = load_sweep(path).runs
        computed = len(configs) - before - journaled
        assert f"{computed} finished, 0 failed, {before + journaled} skipped" in resumed.stdout
        kids, parents = children(uri, "outage")
        finished_once(kids, configs)
        assert not (tmp_path / "mpe3d-journal").exists()  # emptied, then tidied away
        assert not (tmp_path / "mlflow.db").exists()  # nothing went to the local default
        client = MlflowClient(uri)
        for run in (r for r in kids if r.info.status == "FINISHED"):  # replayed ones too
            assert {a.path for a in client.list_artifacts(run.info.run_id)} - {"stress_history.csv"} \
                == {"reconstruction.ply", "ground_truth.ply", "comparison.png"}
        monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
        assert main(["runs", "outage", "--format", "csv"]) == 0
        assert capsys.readouterr().out.count("FINISHED") == len(configs)
    finally:
        stop(second)
    assert main(["sweep", str(path), "--tracking-uri", uri]) == 3  # the store's fault, not the input's
    assert "cannot reach the MLflow tracking server" in capsys.readouterr().err


# -- determinism ----------------------------------------------------------------------

DETERMINISM = """
name: same
base: {shape: airplane, points: 256, views: 4, visibility: {mode: exact, k: 3},
       solver: {name: sgd, max_iter: 40}}
grid: {projections: [fixed, variable]}
repeats: 2
"""


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_jobs_1_jobs_2_and_dask_are_bit_identical(tmp_path):
    path = tmp_path / "same.yaml"
    path.write_text(DETERMINISM)
    results = {}
    for name, flags in {"serial": ["--jobs", "1"], "loky": ["--jobs", "2"],
                        "dask": ["--backend", "dask", "--jobs", "2"]}.items():
        uri = f"sqlite:///{tmp_path}/{name}.db"
        out = run_cli("sweep", str(path), *flags, "--tracking-uri", uri, "--no-artifacts", "--quiet")
        assert out.returncode == 0, out.stderr
        client = MlflowClient(uri)
        kids, _ = children(uri, "same")
        results[name] = {r.data.tags[HASH_TAG]: (
            {k: r.data.metrics[k] for k in ("cd", "emd", "roa", "stress", "iterations")},
            [m.value for m in sorted(client.get_metric_history(r.info.run_id, "stress_history"),
                                     key=lambda m: m.step)]) for r in kids}
    assert len(results["serial"]) == 4
    assert results["loky"] == results["serial"]  # exact equality, not approx: every bit
    assert results["dask"] == results["serial"]


# -- a disk that fills up mid-sweep -----------------------------------------------------

FULL = "name: full\nbase: {shape: chair, points: 400, views: 5, solver: refine}\nrepeats: %d\n"


def check_stopped_for_space(code, err, uri, configs, folder):
    lines = err.strip().splitlines()
    assert code == 3 and len(lines) == 1 and "Traceback" not in err, err
    assert "no space left at" in lines[0] and "free" in lines[0] and "need" in lines[0], lines[0]
    kids, parents = children(uri, "full")
    assert "RUNNING" not in {r.info.status for r in kids + parents}
    done = {r.data.tags[HASH_TAG] for r in kids if r.info.status == "FINISHED"}
    assert 0 < len(done) < len(configs)
    return len(done) + Journal(folder / "mpe3d-journal").pending(uri)


def test_a_full_disk_mid_sweep_is_one_line_and_the_rerun_completes(tmp_path, capsys, monkeypatch):
    """An injected ENOSPC where MLflow copies a run's artifacts, from the 6th run on."""
    import errno

    from mpe3d.harness.tracking.store import Tracker

    path = tmp_path / "full.yaml"
    path.write_text(FULL % 12)
    uri = f"sqlite:///{tmp_path}/t.db"
    monkeypatch.chdir(tmp_path)
    calls = {"n": 0}
    real = Tracker.log_artifacts

    def fill_up(self, run_id, record, artifacts):
        calls["n"] += 1
        if calls["n"] > 5:
            raise OSError(errno.ENOSPC, "No space left on device", "/tmp/x.ply",
                          None, str(tmp_path / "mlartifacts" / run_id / "x.ply"))
        return real(self, run_id, record, artifacts)
    monkeypatch.setattr(Tracker, "log_artifacts", fill_up)
    code = main(["sweep", str(path), "--jobs", "1", "--quiet", "--tracking-uri", uri])
    kept = check_stopped_for_space(code, capsys.readouterr().err, uri, load_sweep(path).runs, tmp_path)
    assert kept == 6  # 5 in the store, and the 6th in the journal: computed, never lost
    monkeypatch.setattr(Tracker, "log_artifacts", real)  # space freed
    assert main(["sweep", str(path), "--jobs", "1", "--quiet", "--tracking-uri", uri]) == 0
    finished_once(children(uri, "full")[0], load_sweep(path).runs)


@pytest.mark.slow
def test_a_tmpfs_that_fills_mid_sweep_is_one_line_and_the_rerun_completes(tmp_path):
    """A real 10 MB filesystem holding the store, its artifacts and the journal."""
    mount = tmp_path / "small"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=10m", "tmpfs", str(mount)],
                          capture_output=True)
    if made.returncode != 0:
        pytest.skip("this machine does not allow a tmpfs mount (the injected ENOSPC test covers it)")
    try:
        path = mount / "full.yaml"
        path.write_text(FULL % 100)
        uri = f"sqlite:///{mount}/mlflow.db"
        argv = ["sweep", str(path), "--jobs", "2", "--quiet", "--tracking-uri", uri]
        first = run_cli(*argv, cwd=mount)  # its stdout and stderr go to pipes, not to the full disk
        configs = load_sweep(path).runs
        check_stopped_for_space(first.returncode, first.stderr, uri, configs, mount)
        subprocess.run(["mount", "-o", "remount,size=80m", str(mount)], check=True)
        again = run_cli(*argv, cwd=mount)
        assert again.returncode == 0, again.stderr
        finished_once(children(uri, "full")[0], configs)
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)
