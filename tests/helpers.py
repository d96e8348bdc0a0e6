"""Helpers shared by the tests."""
import importlib.util
import os
import socket
import subprocess
import sys
import time
import urllib.request
from fractions import Fraction
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from mpe3d.harness.experiment.config import make_config
from mpe3d.harness.scene.observe import build_scene, observe, seed_streams
from mpe3d.harness.shutdown import stop_group

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
# the repository's folders, by the package each installs as (pyproject.toml's package-dir)
PACKAGE_DIRS = {"mpe3d": REPO / "src" / "mpe3d", "mpe3d.harness": REPO / "harness",
                "mpe3d.solvers": REPO / "solvers", "mpe3d.reports": REPO / "reports",
                "mpe3d.sweeps": REPO / "sweeps"}


def load_script(path: str, name: str):
    """A script of the repository that is not in the package (``benchmarks/``,
    ``scripts/``), imported as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, REPO / path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def scene_and_observations(**overrides):
    """A scene and its observations for a small default config."""
    config = make_config({"shape": "torus", "points": 128, **overrides})
    streams = seed_streams(config["seed"])
    scene = build_scene(config, streams)
    obs, _ = observe(scene, config, streams)
    return config, scene, obs


def mpe3d_command() -> list[str]:
    """The installed ``mpe3d`` console script, as a user runs it (falls back to
    ``python -m mpe3d.cli`` when the package is not installed)."""
    script = Path(sys.executable).parent / "mpe3d"
    return [str(script)] if script.exists() else [sys.executable, "-m", "mpe3d.cli"]


def new_store(uri: str) -> None:
    """Create a SQLite store before a sweep in another process uses it. A test that
    polls a store the sweep is still creating runs MLflow's migrations twice at once
    (``table _alembic_tmp_experiments already exists``); the sweep takes a lock for
    that, a bare client does not. ``Tracker`` takes the same lock."""
    from mpe3d.harness.tracking.store import Tracker

    Tracker(uri)


def run_cli(*args, cwd=None, env=None):
    """Run ``mpe3d`` in a subprocess and capture what a user would see."""
    inherited = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env = {**inherited, "PYTHONWARNINGS": "ignore", **(env or {})}  # tests pick their store
    return subprocess.run([*mpe3d_command(), *args], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=300)


def random_views(rng, model: str, n_points: int, n_views: int, *, turn: float, noise: float,
                 keep: float = 1.0):
    """A random cloud seen by random cameras of ``model`` (rotations of about
    ``turn`` radians, zooms, shifts; pinholes of focal 1500 px): X, the cameras,
    and each observation's view, point and noisy 2D point, a ``keep`` share kept."""
    import numpy as np

    from mpe3d.solvers.sfm.cameras import affine_cameras, exp_so3

    X = rng.standard_normal((n_points, 3)) * 100
    R = exp_so3(turn * rng.standard_normal((n_views, 3)))
    cameras = affine_cameras(model, R[:, :2], np.exp(0.2 * rng.standard_normal(n_views)),
                             320 + 20 * rng.standard_normal((n_views, 2)), focal=1500.0,
                             principal_point=[320.0, 240.0])
    view, point = np.repeat(np.arange(n_views), n_points), np.tile(np.arange(n_points), n_views)
    if keep < 1.0:
        seen = rng.random(len(view)) < keep
        view, point = view[seen], point[seen]
    z = cameras.project(X, view, point) + noise * rng.standard_normal((len(view), 2))
    return X, cameras, view, point, z


# -- real servers on 127.0.0.1 ----------------------------------------------------

def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(url, process, seconds=120):
    deadline = time.time() + seconds
    while time.time() < deadline:
        assert process.poll() is None, "the server died while starting"
        try:
            with urllib.request.urlopen(url, timeout=2) as answer:
                if answer.status == 200:
                    return
        except OSError:
            time.sleep(0.3)
    raise TimeoutError(url)


def stop(process):
    """Stop a server started in its own session, its workers with it."""
    stop_group(process, grace_s=20)


def short_track_set(folder, seed: int = 0, n_points: int = 544, n_views: int = 5, noise: float = 0.3):
    """Keypoints of a real-photo-like set with short tracks, written to ``folder``
    as keypoints.csv, points.csv (the reference) and cameras.npy: pinholes of
    focal 1500 px turning 10 degrees a view round a cloud at 4 units, each
    point seen in 2 (40%) or 3 neighbouring views (2.6 views a track), with
    ``noise`` pixels of Gaussian noise."""
    import numpy as np
    import pandas as pd

    from mpe3d.solvers.sfm.cameras import exp_so3

    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n_points, 3)) * [1.0, 0.7, 0.5]
    K = np.array([[1500.0, 0, 960], [0, 1500.0, 640], [0, 0, 1]])
    P = np.stack([K @ np.c_[exp_so3(np.array([[0.0, np.radians(10.0 * k - 20.0), 0.0]]))[0], [0, 0, 4.0]]
                  for k in range(n_views)])
    rows = []
    for i in range(n_points):
        length = 2 if rng.random() < 0.4 else 3
        first = rng.integers(0, n_views - length + 1)
        for k in range(first, first + length):
            h = P[k] @ np.r_[X[i], 1.0]
            rows.append((k, i, *(h[:2] / h[2] + noise * rng.standard_normal(2))))
    pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(folder / "keypoints.csv", index=False)
    pd.DataFrame({"id": np.arange(n_points), "x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}).to_csv(
        folder / "points.csv", index=False)
    np.save(folder / "cameras.npy", P)
    return folder


def close_up_keypoints(n=300, views=8, distance=0.9, orthographic=False):
    """Keypoints of a cloud from cameras close to it: pinhole photos no
    orthographic projection fits (or, ``orthographic``, their weak twin)."""
    from mpe3d.harness.scene.rendering import spiral_cameras

    rng = np.random.default_rng(0)
    X = 0.25 * rng.normal(size=(n, 3))
    cameras = spiral_cameras(views, distance=distance, turns=0.25)
    out = []
    for R, t in zip(cameras.rotations, cameras.translations):
        x = X @ R.T + t
        depth = x[:, 2:] if not orthographic else np.full((n, 1), float(np.mean(x[:, 2])))
        xy = cameras.focal * x[:, :2] / depth + 200.0 + 0.3 * rng.normal(size=(n, 2))
        out.append({"ids": np.arange(n), "xy": xy})
    return out


def children(uri, experiment):
    """A sweep's child runs and its parent runs in an MLflow store."""
    from mlflow.tracking import MlflowClient

    from mpe3d.harness.tracking.store import PARENT_TAG

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    runs = client.search_runs([exp.experiment_id], max_results=5000)
    return [r for r in runs if PARENT_TAG in r.data.tags], [r for r in runs if PARENT_TAG not in r.data.tags]


def finished_once(kids, configs):
    """Every config has exactly one FINISHED run, and no run is left RUNNING."""
    from collections import Counter

    from mpe3d.harness.tracking.store import HASH_TAG

    done = Counter(r.data.tags[HASH_TAG] for r in kids if r.info.status == "FINISHED")
    assert set(done) == {c.hash() for c in configs}
    assert set(done.values()) == {1}, done.most_common(3)
    assert "RUNNING" not in {r.info.status for r in kids}



def exact_fma(a: float, b: float, c: float) -> float:
    """a * b + c rounded once (exact arithmetic, then one rounding to float)."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def blas_fuses_small_products() -> bool:
    """Whether numpy's BLAS forms a small product (3 x 3 @ 3 x 7) as one chain
    of fused multiply-adds along the inner index, from its first product, as
    x86 OpenBLAS does: then the kernels that copy that chain must give
    numpy's bits, not just its values."""
    rng = np.random.default_rng(0)
    A, B = rng.standard_normal((40, 3, 3)), rng.standard_normal((40, 3, 7))
    chained = [[[exact_fma(A[t, i, 2], B[t, 2, j], exact_fma(A[t, i, 1], B[t, 1, j], A[t, i, 0] * B[t, 0, j]))
                 for j in range(7)] for i in range(3)] for t in range(40)]
    return np.array_equal(A @ B, np.array(chained))


def scaled_track_set(folder, n_points=60, n_views=5, seed=3):
    """Keypoints of a random cloud through scaled orthographic cameras (exact,
    no noise), its points as reference, and pinhole-free cameras."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n_points, 3))
    rows = []
    for k in range(n_views):
        R = Rotation.from_euler("yx", [25.0 * k - 50.0, 10.0 * (k % 2)], degrees=True).as_matrix()
        uv = 120.0 * X @ R[:2].T + [320.0 + 5 * k, 240.0]
        rows += [(f"v{k}", i, *uv[i]) for i in range(n_points)]
    folder.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows, columns=["view", "point", "x", "y"]).to_csv(folder / "keypoints.csv", index=False)
    pd.DataFrame({"id": range(n_points), "x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}).to_csv(
        folder / "points.csv", index=False)
    return X


def similarity_residuals(X, truth, mirror: bool = False) -> np.ndarray:
    """Each point's distance to its true position after the best similarity
    (:func:`mpe3d.harness.scene.metrics.similarity_transform`, Umeyama's):
    the one alignment of the tests. ``mirror`` allows a reflection, for the
    cameras that cannot tell a shape from its mirror image (orthographic)."""
    from mpe3d.harness.scene.metrics import similarity_transform

    X, truth = np.asarray(X, dtype=float), np.asarray(truth, dtype=float)
    s, Q, t = similarity_transform(X, truth, mirror=mirror)
    return np.linalg.norm(s * X @ Q.T + t - truth, axis=1)


def similarity_rms(X, truth, mirror: bool = False) -> float:
    """The RMS of :func:`similarity_residuals`."""
    return float(np.sqrt(np.mean(similarity_residuals(X, truth, mirror) ** 2)))


def pyproject() -> dict:
    """pyproject.toml, parsed (tomllib, or tomli before Python 3.11)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def assert_contract_fails(check, plugin_file, name: str, expected) -> None:
    """Load a broken plug-in and hold ``check(name)`` (a contract check) to
    failing in one line per failure, naming each ``expected`` part."""
    from mpe3d import plugins

    plugins.load_file(plugin_file)
    failures = check(name)
    assert failures, f"{name} passed"
    text = "\n".join(failures)
    for part in expected:
        assert part in text, text
    assert all("\n" not in line and line.startswith("FAIL ") for line in failures)
