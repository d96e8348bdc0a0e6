"""Ctrl-C, twice, SIGINT and SIGTERM stop a real sweep the same way: exit 130
within 10 s, the one line last, no process left, and a rerun that completes
every config exactly once. ``scripts/interrupt_trials.py`` runs many trials."""
import random

import pytest

from tests.harness.interrupts import EXIT_S, LAST_LINE, MOMENTS, trial


def check(outcome) -> None:
    assert not outcome.too_late, "the sweep was over before the signal: make it longer"
    assert not outcome.hung, f"still alive {EXIT_S} s after {outcome.how} at {outcome.moment}"
    assert outcome.exit_code == 130, outcome
    assert outcome.last_line == LAST_LINE, outcome.last_line
    assert not outcome.left_alive, f"processes left: {outcome.left_alive}"
    assert outcome.rerun_code == 0, outcome
    assert (outcome.lost, outcome.computed_twice, outcome.missing) == (0, 0, 0), outcome


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_ctrl_c_mid_run_stops_cleanly_and_the_rerun_completes(tmp_path):
    check(trial(tmp_path, "running", random.Random(0), how="group-sigint", repeats=24))
    assert not (tmp_path / "mpe3d-journal").exists()  # emptied and tidied away


@pytest.mark.slow
@pytest.mark.parametrize("moment,how", zip(MOMENTS, ("double-sigint", "sigterm", "group-sigint",
                                                     "double-sigint")))
def test_every_moment_and_every_way_to_stop(tmp_path, moment, how):
    """Each moment once, each way to stop at least once (the many-trial
    measurement is scripts/interrupt_trials.py)."""
    check(trial(tmp_path, moment, random.Random(hash((moment, how)) % 1000), how=how, repeats=16))


@pytest.mark.slow  # (test_store's UI test stops it by `kill PID` in the default run)
def test_ui_stops_on_ctrl_c_with_its_server(tmp_path):
    """`mpe3d ui` in its own session, Ctrl-C to the group: 130, one line, no server left."""
    import os
    import signal
    import subprocess
    import time

    import psutil

    from tests.helpers import free_port, mpe3d_command, wait_for

    port = free_port()
    ui = subprocess.Popen([*mpe3d_command(), "ui", "--port", str(port), "--tracking-uri",
                           f"sqlite:///{tmp_path}/t.db"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True, start_new_session=True)
    wait_for(f"http://127.0.0.1:{port}/health", ui)
    family = psutil.Process(ui.pid).children(recursive=True)
    sent = time.time()
    os.killpg(ui.pid, signal.SIGINT)
    _, err = ui.communicate(timeout=EXIT_S)
    assert time.time() - sent < EXIT_S and ui.returncode == 130
    assert err.strip().splitlines()[-1] == "mpe3d: interrupted; the MLflow UI is stopped"
    _, alive = psutil.wait_procs(family, timeout=EXIT_S)
    assert not alive, [p.pid for p in alive]


@pytest.mark.slow
@pytest.mark.parametrize("jobs,backend", [(2, "dask"), (1, "loky")])
def test_a_dask_cluster_and_a_single_job_stop_the_same_way(tmp_path, jobs, backend):
    check(trial(tmp_path, "running", random.Random(jobs), how="group-sigint", repeats=16,
                jobs=jobs, backend=backend))


def test_a_command_that_is_over_leaves_even_when_an_exit_hook_hangs():
    """An exit hook that never returns (as loky's or SQLite's once did after a
    full disk stopped a sweep) cannot keep the process: it leaves with its code."""
    import subprocess
    import sys
    import time

    script = ("import atexit, time\n"
              "from mpe3d.harness import shutdown\n"
              "shutdown.FINALISE_S = 1.0\n"
              "atexit.register(time.sleep, 600)\n"
              "shutdown.Shutdown().__enter__().settle(3)\n")
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert done.returncode == 3 and time.monotonic() - start < 30, done
