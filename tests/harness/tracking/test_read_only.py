"""A store on a read-only mount (a colleague's share, an archive): the
commands that read it (runs, report, ui) open it read-only; a command that
writes refuses it in one line."""
import json
import subprocess
import urllib.request

import pytest

from tests.helpers import free_port, mpe3d_command, run_cli, stop, wait_for

SWEEP = "name: read-only\nbase: {points: 40, solver: refine}\ngrid:\n  views: [3, 4]\n"


@pytest.fixture(scope="module")
def mounted(tmp_path_factory):
    """A tracked sweep, and the same store seen through a read-only bind mount."""
    root = tmp_path_factory.mktemp("read-only")
    source, view = root / "source", root / "view"
    source.mkdir()
    view.mkdir()
    (root / "s.yaml").write_text(SWEEP)
    done = run_cli("sweep", str(root / "s.yaml"), "--jobs", "1", "--quiet", "--no-artifacts",
                   "--tracking-uri", f"sqlite:///{source}/mlflow.db", cwd=root)
    assert done.returncode == 0, done.stderr
    bind = subprocess.run(["mount", "--bind", str(source), str(view)], capture_output=True)
    if bind.returncode != 0:
        pytest.skip(f"needs a bind mount (root): {bind.stderr.decode().strip()}")
    try:
        subprocess.run(["mount", "-o", "remount,bind,ro", str(view)], check=True, capture_output=True)
        yield root, f"sqlite:///{view}/mlflow.db"
    finally:
        subprocess.run(["umount", str(view)], capture_output=True)


def test_runs_and_report_read_a_store_on_a_read_only_mount(mounted):
    root, uri = mounted
    runs = run_cli("runs", "read-only", "--format", "json", "--tracking-uri", uri, cwd=root)
    assert runs.returncode == 0, runs.stderr
    assert sorted(row["views"] for row in json.loads(runs.stdout)) == [3, 4]
    report = run_cli("report", "--experiment", "read-only", "--out", str(root / "report"),
                     "--tracking-uri", uri, cwd=root)
    assert report.returncode == 0, report.stderr
    assert (root / "report" / "index.html").is_file()


def test_a_sweep_refuses_a_read_only_store_in_one_line(mounted):
    root, uri = mounted
    done = run_cli("sweep", str(root / "s.yaml"), "--jobs", "1", "--force", "--tracking-uri", uri, cwd=root)
    assert done.returncode != 0
    assert done.stderr.strip().count("\n") == 0 and "Read-only file system" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_ui_serves_a_store_on_a_read_only_mount(mounted):
    root, uri = mounted
    port = free_port()
    server = subprocess.Popen([*mpe3d_command(), "ui", "--tracking-uri", uri, "--port", str(port)],
                              cwd=root, start_new_session=True, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        wait_for(f"http://127.0.0.1:{port}/health", server)
        request = urllib.request.Request(f"http://127.0.0.1:{port}/api/2.0/mlflow/experiments/search",
                                         data=b'{"max_results": 10}', method="POST",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as answer:
            names = [e["name"] for e in json.loads(answer.read())["experiments"]]
        assert "read-only" in names
    finally:
        stop(server)
