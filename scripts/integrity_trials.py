"""Adversarial trials of mpe3d's integrity, one JSON line per trial kind.

    python scripts/integrity_trials.py [--kill 8] [--concurrent 8] [--outage 3] [--hostile]

- hostile: a corpus of bad inputs to every command; each must get exactly one
  ``mpe3d: error:`` line, exit 2, no traceback, nothing written, within 60 s;
- kill: a sweep killed with SIGKILL at a random moment, then run again: no run
  left RUNNING, every config FINISHED exactly once, nothing logged lost;
- concurrent: two sweeps of one experiment started together on a new store:
  both succeed, every config computed once;
- outage: the tracking server killed (connections refused) or hung (SIGSTOP:
  requests time out) mid-sweep, then restarted: the sweep stops within 30 s
  with one error line, and the rerun loses nothing and computes nothing twice.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np

MPE3D = [str(Path(sys.executable).parent / "mpe3d")]
SWEEP = """name: {name}
base: {{shape: torus, points: {points}, views: 4, solver: {{name: sgd, max_iter: 40, tol: 1.0e-15}}}}
grid: {{projections: [fixed, variable]}}
repeats: {repeats}
"""


# -- hostile inputs ---------------------------------------------------------------

XY = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]


def _npz(path, **arrays):
    base = {"view0_ids": np.arange(4), "view0_xy": np.array(XY), "view1_ids": np.arange(4),
            "view1_xy": np.array(XY)}
    np.savez(path, **{**base, **arrays})


def _csv(rows, header="view,point,x,y"):
    return header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows)


GOOD_ROWS = [(k, i, x, y) for k in (0, 1) for i, (x, y) in enumerate(XY)]


def hostile_cases():
    """(name, files to write, argv). Files: name -> str | bytes | callable(path)."""
    rec = lambda src, *extra: ["reconstruct", src, "--out", "out.ply", "--report", "r.json", *extra]  # noqa: E731
    cases = []
    csv_texts = {
        "csv-empty": "", "csv-header-only": "view,point,x,y\n", "csv-missing-y": "view,point,x\n0,1,0\n",
        "csv-dup-column": "view,point,x,y,x\n0,1,0,0,1\n", "csv-nan": _csv([(0, 1, "nan", 0)] + GOOD_ROWS[1:]),
        "csv-inf": _csv([(0, 1, "inf", 0)] + GOOD_ROWS[1:]), "csv-text": _csv([(0, 1, "abc", 0)] + GOOD_ROWS[1:]),
        "csv-dup-point": _csv(GOOD_ROWS + [(0, 1, 5, 5)]), "csv-one-view": _csv(GOOD_ROWS[:4]),
        "csv-two-points": _csv([(0, 1, 0, 0), (0, 2, 1, 1)] + GOOD_ROWS[4:]),
        "csv-huge-id": _csv([(k, 10**25 if i == 0 else i, x, y) for k, i, x, y in GOOD_ROWS]),
        "csv-ragged": "view,point,x,y\n0,1,0\n0,2,1,1,1,1\n", "csv-binary": os.urandom(2000),
        "csv-utf16": _csv(GOOD_ROWS).encode("utf-16"), "csv-no-shared": _csv(
            [(0, i, x, y) for i, (x, y) in enumerate(XY)] + [(1, i + 10, x, y) for i, (x, y) in enumerate(XY)]),
        "csv-1e400": _csv([(0, 1, "1e400", 0)] + GOOD_ROWS[1:]), "csv-only-commas": ",,,\n,,,\n",
    }
    for name, text in csv_texts.items():
        cases.append((name, {"in.csv": text}, rec("in.csv")))
    views = lambda first, ids=(0, 1, 2, 3): {"views": [{"ids": list(ids), "xy": first},  # noqa: E731
                                                       {"ids": [0, 1, 2, 3], "xy": XY}]}
    json_texts = {
        "json-deep": "[" * 200_000 + "]" * 200_000, "json-latin1": json.dumps(views(XY)).encode("utf-16"),
        "json-ragged": json.dumps(views([[0, 0], [1, 0, 2], [0, 1], [1, 1]])),
        "json-bool": json.dumps(views([[0, 0], [True, 0], [0, 1], [1, 1]])),
        "json-bool-ids": json.dumps(views(XY, (0, False, 2, 3))),
        "json-string-number": json.dumps(views([[0, 0], ["1", 0], [0, 1], [1, 1]])),
        "json-null": json.dumps(views([[0, 0], [None, 0], [0, 1], [1, 1]])),
        "json-big-id": json.dumps(views(XY, (0, 1, 2, 10**40))), "json-nested-ids": json.dumps(views(XY, ([0], 1, 2, 3))),
        "json-no-views": json.dumps({"cams": []}), "json-views-dict": json.dumps({"views": {"a": 1}}),
        "json-view-list": json.dumps({"views": [[1, 2], [3]]}), "json-both": json.dumps(
            {"views": [{"ids": [0, 1, 2], "xy": XY[:3], "dist": [[0, 1, 1], [1, 0, 1], [1, 1, 0]]}, {"ids": [0, 1, 2], "xy": XY[:3]}]}),
        "json-malformed": '{"views": [', "json-empty": "", "json-huge-float": json.dumps(views([[0, 0], [1e308 * 10, 0], [0, 1], [1, 1]])).replace("Infinity", "1e999"),
        "json-dist-asym": json.dumps({"views": [{"ids": [0, 1, 2], "dist": [[0, 1, 2], [1, 0, 1], [2, 3, 0]]}, {"ids": [0, 1, 2], "dist": [[0, 1, 2], [1, 0, 1], [2, 1, 0]]}]}),
        "json-dist-negative": json.dumps({"views": [{"ids": [0, 1, 2], "dist": [[0, -1, 2], [-1, 0, 1], [2, 1, 0]]}, {"ids": [0, 1, 2], "dist": [[0, 1, 2], [1, 0, 1], [2, 1, 0]]}]}),
        "json-dist-not-square": json.dumps({"views": [{"ids": [0, 1, 2], "dist": [[0, 1], [1, 0], [2, 1]]}, {"ids": [0, 1, 2], "dist": [[0, 1, 2], [1, 0, 1], [2, 1, 0]]}]}),
    }
    for name, text in json_texts.items():
        cases.append((name, {"in.json": text}, rec("in.json")))

    def truncated(path):
        _npz(path)
        path.write_bytes(path.read_bytes()[:300])

    def crc(path):
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
            for key, value in (("view0_ids", np.arange(4)), ("view0_xy", np.array(XY)),
                               ("view1_ids", np.arange(4)), ("view1_xy", np.array(XY) + 7)):
                with archive.open(key + ".npy", "w") as handle:
                    np.lib.format.write_array(handle, value)
        data = bytearray(path.read_bytes())
        data[data.rfind((np.array(XY) + 7).tobytes()[:8]) + 2] ^= 0xFF
        path.write_bytes(bytes(data))

    def declared_huge(path):
        _npz(path)
        with zipfile.ZipFile(path, "a") as archive:
            with archive.open("view2_dist.npy", "w") as handle:
                np.lib.format.write_array_header_1_0(
                    handle, {"descr": "<f8", "fortran_order": False, "shape": (10**6, 10**6)})
            with archive.open("view2_ids.npy", "w") as handle:
                np.lib.format.write_array(handle, np.arange(4))

    npz_makers = {
        "npz-truncated": truncated, "npz-crc": crc, "npz-declared-huge": declared_huge,
        "npz-object": lambda p: _npz(p, view1_xy=np.array([None] * 8, dtype=object)),
        "npz-bool": lambda p: _npz(p, view1_xy=np.array(XY) > 0.5),
        "npz-complex": lambda p: _npz(p, view1_xy=np.array(XY) * 1j),
        "npz-strings": lambda p: _npz(p, view1_xy=np.array(XY).astype(str)),
        "npz-wrong-shape": lambda p: _npz(p, view1_xy=np.zeros((4, 3))),
        "npz-nan": lambda p: _npz(p, view1_xy=np.array(XY) * np.nan),
        "npz-both": lambda p: _npz(p, view1_dist=np.zeros((4, 4))),
        "npz-no-ids": lambda p: np.savez(p, view0_xy=np.array(XY), view1_xy=np.array(XY)),
        "npz-not-zip": lambda p: p.write_bytes(b"PK\x03\x04" + os.urandom(500)),
        "npz-empty": lambda p: p.write_bytes(b""), "npz-empty-archive": lambda p: np.savez(p),
        "npz-3d-ids": lambda p: _npz(p, view1_ids=np.zeros((2, 2, 1), int)),
    }
    for name, make in npz_makers.items():
        cases.append((name, {"in.npz": make}, rec("in.npz")))
    good = {"in.csv": _csv(GOOD_ROWS)}
    projections = {
        "proj-count": np.tile(np.eye(3)[:2], (3, 1, 1)), "proj-shape": np.zeros((2, 3, 2)),
        "proj-not-orthonormal": np.tile([[1.0, 0, 0], [1.0, 1, 0]], (2, 1, 1)),
        "proj-nan": np.full((2, 2, 3), np.nan), "proj-object": np.array([None, None], dtype=object),
    }
    for name, value in projections.items():
        cases.append((name, {**good, "P.npy": lambda p, v=value: np.save(p, v, allow_pickle=True)},
                      rec("in.csv", "--projections", "P.npy")))
    cases += [
        ("proj-json-deep", {**good, "P.json": "[" * 100_000 + "]" * 100_000}, rec("in.csv", "--projections", "P.json")),
        ("proj-truncated", {**good, "P.npy": lambda p: (np.save(p, np.zeros((2, 2, 3))), p.write_bytes(p.read_bytes()[:90]))},
         rec("in.csv", "--projections", "P.npy")),
        ("proj-missing", good, rec("in.csv", "--projections", "nope.npy")),
        ("proj-txt", {**good, "P.txt": "1 0 0"}, rec("in.csv", "--projections", "P.txt")),
    ]
    paths = {
        "out-folder": ["reconstruct", "in.csv", "--out", "."], "out-folder-ply": ["reconstruct", "in.csv", "--out", "d.ply"],
        "out-unwritable": ["reconstruct", "in.csv", "--out", "/proc/x.ply"],
        "out-missing-folder": ["reconstruct", "in.csv", "--out", "no/such/x.ply"],
        "out-format": ["reconstruct", "in.csv", "--out", "x.obj"],
        "report-missing-folder": ["reconstruct", "in.csv", "--out", "x.ply", "--report", "no/r.json"],
        "report-unwritable": ["reconstruct", "in.csv", "--out", "x.ply", "--report", "/proc/r.json"],
        "report-folder": ["reconstruct", "in.csv", "--out", "x.ply", "--report", "d.ply"],
        "report-format": ["reconstruct", "in.csv", "--out", "x.ply", "--report", "r.txt"],
        "seed-negative": ["reconstruct", "in.csv", "--out", "x.ply", "--seed", "-3"],
        "seed-text": ["reconstruct", "in.csv", "--out", "x.ply", "--seed", "abc"],
        "input-missing": ["reconstruct", "none.csv", "--out", "x.ply"],
        "input-device": ["reconstruct", "/dev/zero", "--out", "x.ply"],
        "input-folder-empty": ["reconstruct", "d.ply", "--out", "x.ply"],
        "solver-unknown": ["reconstruct", "in.csv", "--out", "x.ply", "--solver", "magic"],
        "loss-without-refine": ["reconstruct", "in.csv", "--out", "x.ply", "--solver", "sgd", "--loss", "huber"],
        "ply-big-ids": ["reconstruct", "big.csv", "--out", "x.ply"],
    }
    big = _csv([(k, 2**40 + i, x, y) for k, i, x, y in GOOD_ROWS])
    for name, argv in paths.items():
        cases.append((name, {**good, "big.csv": big, "d.ply": "DIR"}, argv))
    sweeps = {
        "yaml-dup-key": "name: x\nbase: {shape: torus}\nbase: {views: 3}\n",
        "yaml-dup-dotted": "base:\n  visibility: {k: 2}\n  visibility.k: 3\n",
        "yaml-dup-grid": "grid:\n  views: [3]\n  views: [4]\n",
        "yaml-grid-1e6": "grid: {views: [2,3,4,5,6,7,8,9,10,11], points: [10,11,12,13,14,15,16,17,18,19]}\nrepeats: 10000\n",
        "yaml-repeats-1e9": "base: {shape: torus}\nrepeats: 1000000000\n",
        "yaml-points-1e9": "base: {shape: torus, points: 1000000000}\n",
        "yaml-100mb": "name: x\n" + "# " + "p" * 100 + "\n" * 1,
        "yaml-deep": "a: " + "[" * 20000 + "]" * 20000 + "\n",
        "yaml-laughs": "".join(f"{c}: &{c} [" + ", ".join([f"*{p}" if p else "x"] * 10) + "]\n"
                               for p, c in zip(["", "a", "b", "c", "d", "e", "f"], "abcdefg")),
        "yaml-python-tag": "name: !!python/object/apply:os.system ['echo pwned > pwned.txt']\n",
        "yaml-not-mapping": "- a\n- b\n", "yaml-binary": os.urandom(3000), "yaml-tabs": "name:\tx\n\tbad: 1\n",
        "yaml-unknown-key": "gird: {views: [2]}\n", "yaml-unknown-run-key": "base: {viws: 3}\n",
        "yaml-bad-type": "grid: {views: [3, many]}\n", "yaml-empty-list": "grid: {views: []}\n",
        "yaml-zip-lengths": "zip: {views: [2, 3], visibility.k: [1]}\n",
        "yaml-seed-twice": "base: {seed: 3}\nrepeats: 2\n", "yaml-negative-seed": "seeds: [-1]\n",
        "yaml-scale-unknown": "scale: {quick: {points: 3}}\n", "yaml-nan-points": "base: {points: .nan}\n",
        "yaml-huge-int": "base: {points: 99999999999999999999999999}\n", "yaml-bool-views": "base: {views: true}\n",
        "yaml-utf16": "name: x\n".encode("utf-16"),
    }
    for name, text in sweeps.items():
        files = {"s.yaml": text}
        if name == "yaml-100mb":
            files = {"s.yaml": lambda p: p.write_bytes(b"name: x\n" + b"# padding line\n" * 7_000_000)}
        cases.append((name, files, ["sweep", "s.yaml", "--dry-run"]))
    runs = {
        "run-points-1e9": ["run", "points=1000000000"], "run-points-3e5": ["run", "points=300000", "visibility.mode=all"],
        "run-unknown-key": ["run", "viws=3"], "run-bad-value": ["run", "points=abc"], "run-no-equals": ["run", "points"],
        "run-config-dup": ["run", "--config", "c.yaml"], "run-config-device": ["run", "--config", "/dev/zero"],
        "run-config-missing": ["run", "--config", "none.yaml"], "run-seed-negative": ["run", "seed=-1"],
        "run-mesh-garbage": ["run", "shape=garbage.ply"], "run-solver-option": ["run", "solver.max_itr=3"],
        "run-nan-fraction": ["run", "noise.fraction=.nan"], "run-angle-zero": ["run", "angle_range=0"],
        "sweep-jobs-zero": ["sweep", "ok.yaml", "--jobs", "0"], "sweep-scheduler-loky": ["sweep", "ok.yaml", "--scheduler", "tcp://x:1", "--backend", "loky"],
        "sweep-max-runs": ["sweep", "ok.yaml", "--max-runs", "1", "--dry-run"],
        "sweep-missing-file": ["sweep", "none.yaml"], "runs-no-store": ["runs", "x", "--tracking-uri", "sqlite:///none.db"],
        "report-no-store": ["report", "--experiment", "x", "--out", "rep", "--tracking-uri", "sqlite:///none.db"],
        "report-bad-sweep": ["report", "--sweep", "c.yaml", "--out", "rep"],
    }
    for name, argv in runs.items():
        cases.append((name, {"c.yaml": "shape: torus\npoints: 64\npoints: 80\n", "garbage.ply": os.urandom(500),
                             "ok.yaml": "base: {shape: torus, points: 32}\nrepeats: 3\n"}, argv))
    return cases


def _write(folder: Path, files: dict) -> None:
    for name, content in files.items():
        path = folder / name
        if content == "DIR":
            path.mkdir()
        elif callable(content):
            content(path)
        else:
            path.write_bytes(content.encode() if isinstance(content, str) else content)


def _snapshot(folder: Path) -> set:
    return {(p.relative_to(folder), p.stat().st_size) for p in folder.rglob("*")}


def hostile(workers: int = 2) -> dict:
    import concurrent.futures as cf

    def one(case):
        name, files, argv = case
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            _write(folder, files)
            before = _snapshot(folder)
            start = time.time()
            try:
                done = subprocess.run([*MPE3D, *argv], cwd=folder, capture_output=True, text=True,
                                      timeout=60, env={**os.environ, "MLFLOW_TRACKING_URI": ""})
            except subprocess.TimeoutExpired:
                return name, "hang (over 60 s)"
            lines = done.stderr.strip().splitlines()
            problems = []
            if done.returncode != 2:
                problems.append(f"exit {done.returncode}")
            if "Traceback" in done.stderr:
                problems.append("traceback")
            if len(lines) != 1 or not lines[0].startswith("mpe3d: error:"):
                problems.append(f"{len(lines)} stderr lines")
            if _snapshot(folder) != before:
                problems.append("wrote files")
            return name, "; ".join(problems) or f"ok ({time.time() - start:.1f} s): {lines[0][14:110]}"

    cases = hostile_cases()
    with cf.ThreadPoolExecutor(workers) as pool:
        results = dict(pool.map(one, cases))
    failed = {k: v for k, v in results.items() if not v.startswith("ok")}
    return {"trial": "hostile", "tried": len(cases), "answered_clearly": len(cases) - len(failed),
            "failed": failed}


# -- processes ---------------------------------------------------------------------

def _children(uri, experiment):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        return []
    return client.search_runs([exp.experiment_id], max_results=5000)


def _audit(uri, experiment, hashes):
    runs = _children(uri, experiment)
    kids = [r for r in runs if "mpe3d.config_hash" in r.data.tags]
    done = Counter(r.data.tags["mpe3d.config_hash"] for r in kids if r.info.status == "FINISHED")
    return {"running_left": sum(r.info.status == "RUNNING" for r in runs),
            "missing": len(set(hashes) - set(done)), "computed_twice": sum(n > 1 for n in done.values())}


def _hashes(path):
    from mpe3d.harness.experiment.sweep import load_sweep

    return [c.hash() for c in load_sweep(path).runs]


def kill_trials(n: int, rng: random.Random) -> dict:
    outcomes = []
    for _ in range(n):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            path = folder / "k.yaml"
            path.write_text(SWEEP.format(name="kill", points=160, repeats=4))
            uri = f"sqlite:///{folder}/t.db"
            sweep = subprocess.Popen([*MPE3D, "sweep", str(path), "--jobs", "2", "--tracking-uri", uri,
                                      "--no-artifacts", "--quiet"], cwd=folder)
            time.sleep(rng.uniform(9, 20))  # past the start (a new store takes ~6 s), into the runs
            sweep.send_signal(signal.SIGKILL)
            sweep.wait()
            logged_before = {r.data.tags["mpe3d.config_hash"] for r in _children(uri, "kill")
                             if r.info.status == "FINISHED" and "mpe3d.config_hash" in r.data.tags}
            left_running = sum(r.info.status == "RUNNING" for r in _children(uri, "kill"))
            again = subprocess.run([*MPE3D, "sweep", str(path), "--jobs", "2", "--tracking-uri", uri,
                                    "--no-artifacts", "--quiet"], cwd=folder, capture_output=True, text=True)
            audit = _audit(uri, "kill", _hashes(path))
            after = {r.data.tags["mpe3d.config_hash"] for r in _children(uri, "kill")
                     if r.info.status == "FINISHED" and "mpe3d.config_hash" in r.data.tags}
            outcomes.append({"exit": again.returncode, "running_after_kill": left_running,
                             "lost": len(logged_before - after), **audit})
    return {"trial": "kill -9", "trials": n, "left_running_by_kill": sum(o["running_after_kill"] > 0 for o in outcomes),
            "running_after_next": sum(o["running_left"] for o in outcomes),
            "lost": sum(o["lost"] + o["missing"] for o in outcomes),
            "computed_twice": sum(o["computed_twice"] for o in outcomes),
            "bad_exit": sum(o["exit"] != 0 for o in outcomes)}


def concurrent_trials(n: int) -> dict:
    outcomes = []
    for _ in range(n):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            path = folder / "c.yaml"
            path.write_text(SWEEP.format(name="both", points=64, repeats=5).replace("sgd", "baseline")
                            .replace(", max_iter: 40, tol: 1.0e-15", ""))
            uri = f"sqlite:///{folder}/new.db"
            command = [*MPE3D, "sweep", str(path), "--jobs", "1", "--tracking-uri", uri, "--no-artifacts", "--quiet"]
            sweeps = [subprocess.Popen(command, cwd=folder, stderr=subprocess.PIPE, text=True) for _ in range(2)]
            errors = [s.communicate()[1] for s in sweeps]
            outcomes.append({"exits": [s.returncode for s in sweeps], **_audit(uri, "both", _hashes(path)),
                             "errors": [e.strip()[:200] for e in errors if e.strip()]})
    return {"trial": "two sweeps at once, new store", "trials": n,
            "bad_exit": sum(o["exits"] != [0, 0] for o in outcomes),
            "computed_twice": sum(o["computed_twice"] for o in outcomes),
            "missing": sum(o["missing"] for o in outcomes), "running_left": sum(o["running_left"] for o in outcomes),
            "errors": [e for o in outcomes for e in o["errors"]]}


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _server(folder, port):
    import urllib.request

    process = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
                                "--workers", "1", "--backend-store-uri", f"sqlite:///{folder}/server.db",
                                "--artifacts-destination", str(folder / "art")],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    for _ in range(300):
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2)
            return process
        except OSError:
            time.sleep(0.3)
    raise TimeoutError("mlflow server did not start")


def _stop(process):
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:  # already gone
        pass
    process.wait()


def outage_trials(n: int, rng: random.Random) -> dict:
    outcomes = []
    for i in range(n):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            port = _free_port()
            uri = f"http://127.0.0.1:{port}"
            path = folder / "o.yaml"
            path.write_text(SWEEP.format(name="outage", points=160, repeats=4))
            server = _server(folder, port)
            sweep = subprocess.Popen([*MPE3D, "sweep", str(path), "--jobs", "2", "--tracking-uri", uri, "--quiet"],
                                     cwd=folder, stderr=subprocess.PIPE, text=True)
            time.sleep(rng.uniform(8, 16))
            logged_before = {r.data.tags["mpe3d.config_hash"] for r in _children(uri, "outage")
                             if r.info.status == "FINISHED" and "mpe3d.config_hash" in r.data.tags}
            mode = ("kill", "hang")[i % 2]
            os.killpg(server.pid, signal.SIGSTOP if mode == "hang" else signal.SIGKILL)
            killed = time.time()
            _, err = sweep.communicate()
            stopped_s = time.time() - killed
            _stop(server)
            journaled = len(list((folder / "mpe3d-journal").glob("*.json")))
            server = _server(folder, port)
            again = subprocess.run([*MPE3D, "sweep", str(path), "--jobs", "2", "--tracking-uri", uri, "--quiet"],
                                   cwd=folder, capture_output=True, text=True)
            audit = _audit(uri, "outage", _hashes(path))
            _stop(server)
            outcomes.append({"mode": mode, "first_exit": sweep.returncode, "stopped_s": round(stopped_s, 1),
                             "error_lines": len(err.strip().splitlines()),
                             **({"stderr": err.strip()[:600]} if len(err.strip().splitlines()) != 1 else {}),
                             "journaled": journaled, "logged_before": len(logged_before),
                             "second_exit": again.returncode, **audit})
    return {"trial": "server outage", "trials": n, "outcomes": outcomes,
            "max_stop_s": max(o["stopped_s"] for o in outcomes),
            "lost": sum(o["missing"] for o in outcomes), "computed_twice": sum(o["computed_twice"] for o in outcomes)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hostile", action="store_true", help="run the hostile-input corpus")
    parser.add_argument("--kill", type=int, default=0, metavar="N")
    parser.add_argument("--concurrent", type=int, default=0, metavar="N")
    parser.add_argument("--outage", type=int, default=0, metavar="N")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not shutil.which(MPE3D[0]):
        parser.error("run from the environment where mpe3d is installed")
    rng = random.Random(args.seed)
    if args.hostile:
        print(json.dumps(hostile()), flush=True)
    if args.kill:
        print(json.dumps(kill_trials(args.kill, rng)), flush=True)
    if args.concurrent:
        print(json.dumps(concurrent_trials(args.concurrent)), flush=True)
    if args.outage:
        print(json.dumps(outage_trials(args.outage, rng)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
