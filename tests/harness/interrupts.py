"""One interrupt trial: a real sweep, in its own session, stopped the way a
user stops it, then audited and resumed. Shared by the interrupt tests and
``scripts/interrupt_trials.py`` (the many-trial measurement).

A trial starts ``mpe3d sweep`` in a new session (its own process group, as a
terminal job is), waits for a chosen moment, sends the signal and checks
what a user would: the command returns within ``EXIT_S`` with 130, stderr
ends with the one line, no process of its tree outlives it by ``EXIT_S``,
and a rerun completes every config exactly once with nothing lost.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from tests.helpers import mpe3d_command

EXIT_S = 10.0
LAST_LINE = "mpe3d: interrupted; every run logged so far is kept: run the same command to resume"
SWEEP = """name: intr
base: {{shape: chair, points: {points}, views: 5, visibility: {{mode: exact, k: 3}},
       solver: {{name: sgd, max_iter: {iters}}}}}
repeats: {repeats}
"""
# When to interrupt: while the store is made and the sweep planned, once runs
# are being logged, or while the journal of a killed sweep is replayed.
MOMENTS = ("planning", "running", "logging", "replay")


@dataclass
class Outcome:
    moment: str
    how: str
    exit_code: int | None = None
    exit_s: float | None = None
    hung: bool = False
    left_alive: list[int] = field(default_factory=list)
    last_line: str = ""
    stderr_tail: str = ""  # the last lines of stderr: what followed our line, if anything
    rerun_code: int | None = None
    rerun_error: str = ""  # the rerun's last line of stderr when it fails
    lost: int = 0
    computed_twice: int = 0
    missing: int = 0
    too_late: bool = False  # every config was logged before the signal: nothing to interrupt

    @property
    def clean(self) -> bool:
        return (not self.hung and self.exit_code == 130 and not self.left_alive
                and self.last_line == LAST_LINE and self.rerun_code == 0
                and not (self.lost or self.computed_twice or self.missing))


def _finished(uri: str, experiment: str) -> Counter:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return Counter()
    runs = client.search_runs([exp.experiment_id], max_results=5000)
    return Counter(r.data.tags["mpe3d.config_hash"] for r in runs
                   if r.info.status == "FINISHED" and "mpe3d.config_hash" in r.data.tags)


def _start(argv, folder: Path) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    return subprocess.Popen([*mpe3d_command(), *argv], cwd=folder, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _journal_entries(folder: Path) -> int:
    return len(list((folder / "mpe3d-journal").glob("*.json")))


def _wait_for(moment: str, sweep: subprocess.Popen, folder: Path, uri: str, rng,
              repeats: int) -> None:
    """Sleep until the trial's ``moment`` (with a random offset inside it)."""
    if moment == "planning":
        time.sleep(rng.uniform(0.5, 4.0))  # importing, opening the store, planning
        return
    deadline = time.time() + 120
    journaled = _journal_entries(folder)
    while time.time() < deadline and sweep.poll() is None:
        if moment == "replay" and _journal_entries(folder) < journaled:
            return  # the journal is being replayed (or was, fast): interrupt now
        if moment in ("running", "logging") and sum(_finished(uri, "intr").values()) >= 1:
            break
        time.sleep(0.05 if moment == "replay" else 0.25)
    if moment == "running":
        # The random offset is cut short once half the configs are logged: on a
        # fast machine the whole sweep could otherwise end inside it.
        until = time.time() + rng.uniform(0.0, 1.5)
        while (time.time() < until and sweep.poll() is None
               and sum(_finished(uri, "intr").values()) < repeats // 2):
            time.sleep(0.1)
    # "logging": at once, when results arrive several a second and each is being logged


def _leave_journal(folder: Path, path: Path, uri: str, count: int) -> None:
    """Results of a sweep that died before logging them: ``count`` computed
    runs in the journal under a dead owner, for the next sweep to replay."""
    import subprocess as sp
    import sys

    from mpe3d.harness.experiment.execute import run_record
    from mpe3d.harness.experiment.sweep import load_sweep
    from mpe3d.harness.tracking.journal import Journal
    from mpe3d.harness.tracking.ownership import Owner

    sweep = load_sweep(path)
    dead = int(sp.run([sys.executable, "-c", "import os; print(os.getpid())"],
                      capture_output=True, text=True).stdout)
    owner = Owner(Owner.current().host, dead, 1.0)
    journal = Journal(folder / "mpe3d-journal")
    for i, config in enumerate(sweep.runs[:count]):
        journal.write(run_record(config, False), {
            "uri": uri, "experiment": sweep.name, "experiment_id": None, "parent_id": "gone",
            "run_id": f"gone{i}", "run_name": sweep.label(config), "owner": owner.tag()})


def trial(folder: Path, moment: str, rng, how: str = "group-sigint", repeats: int = 60,
          points: int = 400, iters: int = 150, jobs: int = 2, backend: str = "loky") -> Outcome:
    """One interrupt of a real sweep at ``moment``, then its audit and rerun.

    ``how``: ``group-sigint`` (a terminal's Ctrl-C), ``sigint`` or ``sigterm``
    (to the main process only), or ``double-sigint`` (Ctrl-C twice, 0.3 s apart).
    ``backend``: loky (the default) or dask (a local cluster of ``jobs`` workers).
    """
    path = folder / "intr.yaml"
    path.write_text(SWEEP.format(points=points, iters=iters, repeats=repeats))
    uri = f"sqlite:///{folder}/t.db"
    argv = ["sweep", str(path), "--jobs", str(jobs), "--tracking-uri", uri, "--no-artifacts",
            "--quiet", "--backend", backend]
    if moment == "replay":
        _leave_journal(folder, path, uri, count=repeats // 2)  # and half left to compute
    before = _finished(uri, "intr")
    sweep = _start(argv, folder)
    tree = psutil.Process(sweep.pid)
    _wait_for(moment, sweep, folder, uri, rng, repeats)
    outcome = Outcome(moment, how)
    if moment != "planning":  # (reading a store being made would race with its migration)
        outcome.too_late = len(_finished(uri, "intr")) == repeats  # nothing left to interrupt
    family = {tree.pid}
    try:
        family |= {p.pid for p in tree.children(recursive=True)}
    except psutil.NoSuchProcess:
        pass
    sent = time.time()
    if how == "group-sigint":
        os.killpg(sweep.pid, signal.SIGINT)
    elif how == "double-sigint":
        os.killpg(sweep.pid, signal.SIGINT)
        time.sleep(0.3)
        os.killpg(sweep.pid, signal.SIGINT)
    else:
        sweep.send_signal(signal.SIGINT if how == "sigint" else signal.SIGTERM)
    try:
        _, err = sweep.communicate(timeout=EXIT_S)
        outcome.exit_code, outcome.exit_s = sweep.returncode, time.time() - sent
    except subprocess.TimeoutExpired:
        outcome.hung = True
        with_kids = [p for p in psutil.process_iter() if p.pid in family]
        for proc in with_kids:
            proc.kill()
        _, err = sweep.communicate()
    lines = [line for line in (err or "").splitlines() if line.strip()]
    outcome.last_line = lines[-1] if lines else ""
    outcome.stderr_tail = "\n".join(lines[-8:])
    _, alive = psutil.wait_procs([p for p in psutil.process_iter() if p.pid in family
                                  and p.pid != sweep.pid], timeout=EXIT_S)
    outcome.left_alive = [p.pid for p in alive]
    for proc in alive:
        proc.kill()
    after_interrupt = _finished(uri, "intr")
    rerun = subprocess.run([*mpe3d_command(), *argv], cwd=folder, capture_output=True, text=True,
                           timeout=600)
    outcome.rerun_code = rerun.returncode
    if rerun.returncode:
        outcome.rerun_error = (rerun.stderr.strip().splitlines() or [""])[-1]
    final = _finished(uri, "intr")
    from mpe3d.harness.experiment.sweep import load_sweep

    hashes = {c.hash() for c in load_sweep(path).runs}
    outcome.lost = len(set(after_interrupt) - set(final)) + len(set(before) - set(final))
    outcome.computed_twice = sum(n > 1 for n in final.values())
    outcome.missing = len(hashes - set(final))
    return outcome


def check(outcome) -> None:
    """A stopped sweep's outcome as the tests require it: exit 130 within EXIT_S, the
    one line last, no process left, and a rerun that completes every config once."""
    assert not outcome.too_late, "the sweep was over before the signal: make it longer"
    assert not outcome.hung, f"still alive {EXIT_S} s after {outcome.how} at {outcome.moment}"
    assert outcome.exit_code == 130, outcome
    assert outcome.last_line == LAST_LINE, outcome.stderr_tail
    assert not outcome.left_alive, f"processes left: {outcome.left_alive}"
    assert outcome.rerun_code == 0, outcome
    assert (outcome.lost, outcome.computed_twice, outcome.missing) == (0, 0, 0), outcome
