"""The examples run as a user runs them, and say what they promise."""
import os
import re
import subprocess
import sys

import pytest

from tests.helpers import REPO, mpe3d_command


def test_keypoints_to_cloud_recovers_the_shape(tmp_path):
    out = subprocess.run([sys.executable, str(REPO / "examples" / "keypoints_to_cloud.py"),
                          "--out", str(tmp_path / "k.csv")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "k.csv").read_text().startswith("view,point,x,y")
    dropped = int(re.search(r"(\d+) wrong matches dropped", out.stdout).group(1))
    error = float(re.search(r"median distance to the true points: ([\d.e-]+)", out.stdout).group(1))
    assert dropped > 0 and error < 0.01, out.stdout  # half-pixel noise on an object ~800 px wide


@pytest.mark.slow  # a wheel, an install, a tiny reproduction: the full suite runs it
def test_the_example_plugin_installs_keeps_the_contract_and_joins_every_table(tmp_path):
    wheels = tmp_path / "wheels"  # built and installed as a user's pip does
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                            "-w", str(wheels), str(REPO / "examples" / "smacof3")],
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr
    # Into a folder of its own on PYTHONPATH: this environment is not touched, and
    # the plug-in meets the mpe3d installed here (its kernels compiled once; the
    # wheel test installs mpe3d itself into a fresh venv)
    plugins = tmp_path / "plugins"
    install = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target",
                              str(plugins), *map(str, wheels.glob("*.whl"))], capture_output=True, text=True,
                             timeout=600)
    assert install.returncode == 0, install.stderr
    env = {**os.environ, "PYTHONWARNINGS": "ignore",
           "PYTHONPATH": os.pathsep.join([str(plugins), *filter(None, [os.environ.get("PYTHONPATH")])])}
    env.pop("MLFLOW_TRACKING_URI", None)
    where = subprocess.run([sys.executable, "-c", "import mpe3d, mpe3d_smacof3; print(mpe3d_smacof3.__file__)"],
                           capture_output=True, text=True, env=env)
    assert where.stdout.startswith(str(plugins)), where.stdout + where.stderr
    mpe3d = mpe3d_command()
    listed = subprocess.run([*mpe3d, "solvers"], capture_output=True, text=True, env=env, timeout=300)
    assert "from plug-in smacof3 (mpe3d-smacof3 0.1.0, entry point" in listed.stdout, listed.stdout
    check = subprocess.run([*mpe3d, "check-solver", "smacof3"], capture_output=True, text=True, env=env,
                           timeout=600)
    assert check.returncode == 0 and "smacof3: 9 of 9 checks pass" in check.stdout, check.stdout
    out = tmp_path / "report"
    paper = subprocess.run([*mpe3d, "reproduce-paper", "--scale", "tiny", "--solver", "smacof3", "--quiet",
                            "--no-artifacts",
                            "--tracking-uri", f"sqlite:///{tmp_path}/t.db", "--out", str(out)],
                           capture_output=True, text=True, env=env, timeout=900, cwd=tmp_path)
    assert paper.returncode == 0, paper.stderr
    index = (out / "index.md").read_text()
    assert "Added method 'smacof3' (plug-in smacof3 (mpe3d-smacof3 0.1.0" in index
    assert "not in paper-smart-init, which compare no solvers" in index
    no_solver_axis = {"smart_init", "colmap_tracks"}  # one solver; COLMAP's own tracks
    tables = {p.stem: p.read_text() for p in (out / "tables").glob("*.md")}
    assert len(tables) >= 14
    for name, text in tables.items():
        if name not in no_solver_axis:
            assert "smacof3" in text, name
    keys = re.findall(r"\]\(figures/(\w+)\.png\)\n\n\*[^\n]*?\* Key: ([^\n]*?)\. \(", index)
    with_methods = [(name, key) for name, key in keys if "3DMPE (paper)" in key]
    assert len(with_methods) >= 8, keys
    assert all("smacof3" in key for _, key in with_methods), with_methods
    header, _, *rows = [line for line in tables["claims"].splitlines() if line.startswith("|")]
    column = [c.strip() for c in header.split("|")].index("smacof3")
    verdicts = [[c.strip() for c in row.split("|")][column] for row in rows]
    assert sum(v.startswith(("holds", "does not hold")) for v in verdicts) >= 5, verdicts  # tested, not n/a
