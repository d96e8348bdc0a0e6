"""Ctrl-C and SIGINT stop the UI, a dask cluster's sweep and a single job's
the same way as test_interrupts.py's sweeps; a command that is over leaves
even when an exit hook hangs."""
import random

import pytest

from tests.harness.interrupts import EXIT_S, check, trial


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
    check(trial(tmp_path, "running", random.Random(jobs), how="group-sigint", repeats=48,
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


def test_workers_are_born_with_ctrl_c_blocked(tmp_path):
    """Ctrl-C reaches the whole process group. A worker it reached before its
    initializer could ignore it died, and the sweep with it: a traceback and
    exit -2, not 130 (a clean-clone CI run hit that moment). Workers are
    started with SIGINT blocked, so there is no such moment, and the sweep's
    own process gets its Ctrl-C as before."""
    import re
    import signal
    from pathlib import Path

    import psutil

    from mpe3d.cli import main

    path = tmp_path / "s.yaml"
    path.write_text("name: s\nbase: {shape: torus, points: 48, solver: baseline}\nrepeats: 2\n")
    assert main(["sweep", str(path), "--jobs", "2", "--quiet", "--no-artifacts",
                 "--tracking-uri", f"sqlite:///{tmp_path}/t.db"]) == 0
    workers = [p for p in psutil.Process().children() if "LokyProcess" in " ".join(p.cmdline())]
    assert len(workers) == 2  # the reusable executor keeps them for the next sweep

    def blocked(status: str) -> bool:
        mask = int(re.search(r"SigBlk:\s*([0-9a-f]+)", status).group(1), 16)
        return bool(mask & (1 << (signal.SIGINT - 1)))
    assert all(blocked(Path(f"/proc/{w.pid}/status").read_text()) for w in workers)
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])  # ours is not
