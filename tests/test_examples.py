"""The examples run as a user runs them, and say what they promise."""
import re
import subprocess
import sys

from tests.helpers import REPO


def test_keypoints_to_cloud_recovers_the_shape(tmp_path):
    out = subprocess.run([sys.executable, str(REPO / "examples" / "keypoints_to_cloud.py"),
                          "--out", str(tmp_path / "k.csv")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "k.csv").read_text().startswith("view,point,x,y")
    dropped = int(re.search(r"(\d+) wrong matches dropped", out.stdout).group(1))
    error = float(re.search(r"median distance to the true points: ([\d.e-]+)", out.stdout).group(1))
    assert dropped > 0 and error < 0.01, out.stdout  # half-pixel noise on an object ~800 px wide
