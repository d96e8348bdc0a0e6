"""A command or a process that ends leaves no process of its own behind: no
loky worker, no resource tracker, however the process leaves."""
import os
import subprocess
import sys
import time
import uuid

import psutil
import pytest

from tests.helpers import mpe3d_command

SWEEP = "name: leftovers\nbase: {points: 40, solver: refine}\ngrid:\n  views: [3, 4, 5]\n"

# A sweep in this process with two workers, then a hard exit without closing
# the pool: how a pytest-xdist worker leaves, which left two loky workers and
# two resource trackers running for good.
IN_PROCESS = """
import os, sys
from mpe3d.cli import main
code = main(["sweep", sys.argv[1], "--jobs", "2", "--quiet", "--no-artifacts", "--tracking-uri", sys.argv[2]])
sys.stdout.flush()
os._exit(code)
"""


def _left(mark: str, seconds: float = 20.0) -> list[str]:
    """The processes still carrying ``mark`` in their environment, once they
    have had ``seconds`` to go."""
    deadline = time.monotonic() + seconds
    while True:
        left = []
        for process in psutil.process_iter(["pid", "cmdline"]):
            try:
                if process.environ().get("MPE3D_TEST_MARK") == mark:
                    left.append(f"{process.pid}: {' '.join(process.info['cmdline'] or [])[:100]}")
            except psutil.Error:
                continue
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.5)


@pytest.mark.parametrize("how", ["command", "in-process, hard exit"])
def test_a_sweep_with_two_workers_leaves_no_process_behind(tmp_path, how):
    (tmp_path / "s.yaml").write_text(SWEEP)
    mark = uuid.uuid4().hex
    env = {**os.environ, "MPE3D_TEST_MARK": mark}
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    if how == "command":
        command = [*mpe3d_command(), "sweep", "s.yaml", "--jobs", "2", "--quiet", "--no-artifacts",
                   "--tracking-uri", uri]
    else:
        command = [sys.executable, "-c", IN_PROCESS, "s.yaml", uri]
    # into files, not pipes: a pipe stays open while a process left behind holds it
    with open(tmp_path / "out", "w") as out, open(tmp_path / "err", "w") as err:
        done = subprocess.run(command, cwd=tmp_path, env=env, stdout=out, stderr=err, timeout=300)
    assert done.returncode == 0, (tmp_path / "err").read_text()
    left = _left(mark)
    for line in left:  # not left for the next test either
        psutil.Process(int(line.split(":")[0])).kill()
    assert not left, left
