"""The installed product: one top-level package, ``mpe3d``, with a small public API."""
import os
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import mpe3d
from mpe3d import solvers
from tests.helpers import PACKAGE_DIRS, REPO

PUBLIC = {"reconstruct", "write_cloud", "solve", "View", "Observations", "run", "make_config",
          "load_sweep", "Tracker",
          # for plug-in authors: the decorators, the option rules, the result type
          "register_solver", "register_dataset", "Interval", "Choice", "Reconstruction",
          # for SfM plug-ins: the decorator and what the method returns
          "register_sfm", "SfmPose", "SfmResult"}


def test_the_public_api_is_small_documented_and_resolves():
    assert set(mpe3d.__all__) == PUBLIC
    for name in mpe3d.__all__:
        value = getattr(mpe3d, name)
        assert value.__doc__ and value.__doc__.strip(), name
        assert name in dir(mpe3d)
    assert mpe3d.solve is solvers.solve and mpe3d.View is solvers.View
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        mpe3d.nope  # noqa: B018
    # The one error type is a ValueError, so Python callers catch it the usual way.
    from mpe3d.errors import MpeError
    with pytest.raises(ValueError, match="points"):
        mpe3d.make_config({"points": 2})
    assert issubclass(MpeError, ValueError)


def test_solvers_import_nothing_from_the_harness():
    for path in (REPO / "solvers").glob("*.py"):
        assert "harness" not in "".join(line for line in path.read_text().splitlines(True)
                                        if line.lstrip().startswith(("import ", "from "))), path


def test_the_wheel_installs_mpe3d_and_nothing_else(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", str(wheels),
                    str(REPO)], check=True, capture_output=True, timeout=600)
    (wheel,) = wheels.glob("mpe3d-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
    top = {name.split("/")[0] for name in names}
    assert top == {"mpe3d", next(t for t in top if t.endswith(".dist-info"))}, top
    for data in ("mpe3d/harness/scene/assets/meshes/chair.ply", "mpe3d/sweeps/paper/views.yaml",
                 "mpe3d/reports/data/paper_tables.csv", "mpe3d/reports/assets/viewer.js"):
        assert data in names, data
    assert not any(name.startswith("mpe3d/tests") for name in names)
    # Only today's modules: setuptools never empties an in-tree build/ folder, so a
    # module moved since the last build would ship twice (and break the layer rule).
    sources = {f"mpe3d/{p.relative_to(folder).as_posix()}" if name == "mpe3d"
               else f"mpe3d/{name.split('.')[1]}/{p.relative_to(folder).as_posix()}"
               for name, folder in PACKAGE_DIRS.items() for p in folder.rglob("*.py")
               if "__pycache__" not in p.parts}
    ghosts = sorted(n for n in names if n.endswith(".py") and n not in sources)
    assert not ghosts, f"stale modules in the wheel (remove build/): {ghosts}"

    # A fresh venv: what installing the wheel adds to its site-packages.
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    before = set(os.listdir(purelib))
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
                    "--no-deps", str(wheel)], check=True, capture_output=True, timeout=600)
    added = set(os.listdir(purelib)) - before
    assert {name for name in added if not name.endswith(".dist-info")} == {"mpe3d"}, added
    assert (venv / "bin" / "mpe3d").exists()

    # The fresh copy answers help() on the public API; this environment lends the dependencies.
    lent = [p for p in [sysconfig.get_paths()["purelib"], *site.getsitepackages()] if Path(p).is_dir()]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(purelib), *lent])}
    shown = subprocess.run([str(python), "-c", "import mpe3d; help(mpe3d.reconstruct); print(mpe3d.__file__)"],
                           capture_output=True, text=True, env=env, timeout=120)
    assert shown.returncode == 0, shown.stderr
    assert "reconstruct(views" in shown.stdout and str(purelib) in shown.stdout
