"""Results you can trust, part one: the code identity that every run is
tagged with sees code, not comments, docstrings or layout; it covers every
module a run loads; and a real edit of an installed copy makes a sweep
recompute exactly the runs that other code made (the rest of the integrity
tests are in test_integrity.py)."""
import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from mpe3d.harness.tracking.identity import code_identity, source_fingerprint
from mpe3d.harness.tracking.store import CODE_TAG
from tests.helpers import REPO, children, run_cli

# -- code identity ------------------------------------------------------------------

CODE = '''
def stress(x):
    """Eq. 1."""
    return x * 2  # doubled
'''


def test_fingerprint_sees_code_not_comments_docstrings_or_layout():
    base = source_fingerprint(CODE)
    assert source_fingerprint(CODE.replace("# doubled", "# twice")) == base
    assert source_fingerprint(CODE.replace('"""Eq. 1."""', '"""Paper Eq. 1, the stress."""')) == base
    assert source_fingerprint(CODE.replace("x * 2", "(x\n            * 2)")) == base
    assert source_fingerprint(CODE.replace("x * 2", "x * 3")) != base
    assert source_fingerprint(CODE.replace("x * 2", "2 * x")) != base


RUN_BOTH_PIPELINES = """
import json, sys
from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.experiment.execute import run_record
for keys in ({"shape": "torus", "points": 64, "views": 3, "solver": "refine"},
             {"pipeline": "colmap", "shape": "chair", "points": 256, "images.count": 10,
              "images.size": 240, "solver": "refine"}):
    record = run_record(make_config(keys), False)
    assert record.status == "FINISHED", record.error
from mpe3d.harness.tracking.identity import fingerprinted_modules
print(json.dumps({"loaded": sorted(m for m in sys.modules if m.split(".")[0] == "mpe3d"),
                  "fingerprinted": sorted(fingerprinted_modules())}))
"""


def test_the_parse_cache_gives_the_identity_a_fresh_parse_gives(tmp_path):
    """A fresh process reads its modules' parses from the cache, keyed by their
    bytes: the same identity as parsing, and a damaged cache is parsed anew."""
    script = "from mpe3d.harness.tracking.identity import code_identity; print(code_identity())"
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}

    def identity():
        out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    assert identity() == code_identity()  # parsed, then cached
    (cache,) = (tmp_path / "mpe3d").glob("identity-*.json")
    entries = json.loads(cache.read_text())
    assert any(key.startswith("mpe3d.solvers.refine:") for key in entries)
    assert identity() == code_identity()  # from the cache
    cache.write_text("{not json")
    assert identity() == code_identity()
    assert json.loads(cache.read_text()).keys() == entries.keys()  # written whole again


def test_every_module_a_run_loads_is_in_the_code_identity():
    """One run of each pipeline, in a fresh process as a worker runs it."""
    out = subprocess.run([sys.executable, "-c", RUN_BOTH_PIPELINES], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.splitlines()[-1])
    # each pipeline is imported when a run asks for it: both did run
    assert {"mpe3d.harness.experiment.points_pipeline",
            "mpe3d.harness.experiment.colmap_pipeline"} <= set(seen["loaded"])
    assert set(seen["loaded"]) <= set(seen["fingerprinted"]), \
        set(seen["loaded"]) - set(seen["fingerprinted"])
    for away in ("mpe3d.cli", "mpe3d.harness.tracking.store", "mpe3d.reports", "mpe3d.sweeps"):
        assert away not in seen["fingerprinted"]


IDENTITY_ALONE = """
import importlib.util, json, sys
from pathlib import Path
from mpe3d.harness.tracking import identity
identity.code_identity()
heavy = sorted(m for m in ("mpe3d.solvers", "sklearn", "ot", "pycolmap") if m in sys.modules)
wrong = [m for m in identity.fingerprinted_modules()
         if identity.module_file(m) != Path(importlib.util.find_spec(m).origin)]
print(json.dumps({"heavy": heavy, "wrong": wrong}))
"""


def test_the_code_identity_finds_its_modules_without_importing_them():
    """Read off the folders: a fresh process pays neither the solvers' nor POT's
    imports for it, and each file is the one Python would import."""
    out = subprocess.run([sys.executable, "-c", IDENTITY_ALONE], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout) == {"heavy": [], "wrong": []}


def test_editing_a_module_on_a_runs_path_changes_the_code_identity(tmp_path, monkeypatch):
    from mpe3d.harness.tracking import identity

    before = identity.code_identity()
    for name, edit in (("mpe3d.harness.userdata.reconstruct", "\nEDITED = 1\n"),
                       ("mpe3d.harness.userdata.formats", "\nEDITED = 1\n"),
                       ("mpe3d.cli.main", None)):  # not on a run's path: no change
        original = identity.module_file(name)
        copy = tmp_path / original.name
        copy.write_text(original.read_text() + (edit or "\ndef extra():\n    return 1\n"))
        monkeypatch.setattr(identity, "module_file",
                            lambda m, name=name, copy=copy, find=identity.module_file:
                            copy if m == name else find(m))
        for cached in (identity.fingerprinted_modules, identity.code_fingerprint, identity.code_identity):
            cached.cache_clear()
        assert (identity.code_identity() != before) == (edit is not None), name
        monkeypatch.undo()
        for cached in (identity.fingerprinted_modules, identity.code_fingerprint, identity.code_identity):
            cached.cache_clear()
    assert identity.code_identity() == before


def copy_checkout(target: Path) -> Path:
    """The project's files (committed or not, never build leftovers) in ``target``."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=REPO, capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        if (REPO / name).is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, target / name)
    return target


def install(source: Path, site: Path) -> dict:
    """``pip install`` the copy into ``site``; the environment that runs it first."""
    shutil.rmtree(site, ignore_errors=True)
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--target", str(site), str(source)], check=True, capture_output=True, timeout=600)
    share_compiled_kernels(site)
    return {"PYTHONPATH": str(site)}


def share_compiled_kernels(site: Path) -> None:
    """Give the installed copy the compiled kernels of the mpe3d under test,
    where its source is the same bytes: numba keys its on-disk cache on the
    source file's path and stamp (mtime, size), so a copy elsewhere compiles
    every kernel again (~25 s) for no test's sake. Left as is where the
    sources differ, or when numba's cache layout changes: that copy compiles."""
    import mpe3d

    ours = Path(mpe3d.__file__).parent
    for cache in ours.rglob("__pycache__/*.nbi"):
        source = cache.parent.parent / (cache.name.split(".", 1)[0] + ".py")
        copy = site / "mpe3d" / source.relative_to(ours)
        if not source.is_file() or not copy.is_file() or copy.read_bytes() != source.read_bytes():
            continue
        stamp = source.stat()
        os.utime(copy, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
        (copy.parent / "__pycache__").mkdir(exist_ok=True)
        for data in cache.parent.glob(cache.name.rsplit(".", 2)[0] + ".*.nbc"):
            shutil.copy2(data, copy.parent / "__pycache__" / data.name)
        shutil.copy2(cache, copy.parent / "__pycache__" / cache.name)


@pytest.mark.slow  # a real sweep or server: the full suite runs it
def test_a_code_change_is_detected_and_recomputed(tmp_path):
    path = tmp_path / "two.yaml"
    path.write_text("name: two\nbase: {shape: torus, points: 48, solver: baseline}\n"
                    "grid: {views: [3, 4]}\n")
    uri = f"sqlite:///{tmp_path}/t.db"
    first = run_cli("sweep", str(path), "--jobs", "1", "--tracking-uri", uri, "--no-artifacts")
    assert first.returncode == 0 and "2 finished" in first.stdout, first.stderr
    source, site = copy_checkout(tmp_path / "src"), tmp_path / "site"
    command = [sys.executable, "-m", "mpe3d.cli", "sweep", str(path), "--jobs", "1",
               "--tracking-uri", uri, "--no-artifacts"]
    env = {**os.environ, **install(source, site)}  # once: the edits below go to the installed copy

    # Comments, docstrings and reports are not code that makes numbers.
    baseline = site / "mpe3d" / "solvers" / "baseline.py"
    baseline.write_text(baseline.read_text().replace('"""', '"""Edited docs. ', 1) + "\n# a note\n")
    tables = site / "mpe3d" / "reports" / "tables.py"
    tables.write_text(tables.read_text() + "\nX = 1\n")
    same = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert same.returncode == 0 and "nothing to run" in same.stdout, same.stdout + same.stderr

    # A solver that computes differently is another code: its runs are recomputed.
    baseline.write_text(baseline.read_text() + "\nEDITED_CONSTANT = 2.0\n")
    edited = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert edited.returncode == 0, edited.stderr
    assert "2 finished" in edited.stdout and "2 of them replaced runs computed by other code" in edited.stdout
    kids, parents = children(uri, "two")
    codes = Counter(r.data.tags[CODE_TAG] for r in kids if r.info.status == "FINISHED")
    assert len(codes) == 2 and set(codes.values()) == {2} and codes[code_identity()] == 2
    assert {p.data.tags[CODE_TAG] for p in parents} == set(codes)
    # Back on the original code, its own runs count again; nothing reruns.
    again = run_cli("sweep", str(path), "--jobs", "1", "--tracking-uri", uri)
    assert "nothing to run" in again.stdout, again.stdout
    table = run_cli("runs", "two", "--tracking-uri", uri, "--history", "--format", "csv")
    assert "2 versions of the code" in table.stderr and code_identity() in table.stdout


