"""Helpers shared by the tests."""
import os
import subprocess
import sys
from pathlib import Path


from mpe3d.harness.config import make_config
from mpe3d.harness.observe import build_scene, observe, seed_streams

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def scene_and_observations(**overrides):
    """A scene and its observations for a small default config."""
    config = make_config({"shape": "torus", "points": 128, **overrides})
    streams = seed_streams(config["seed"])
    scene = build_scene(config, streams)
    obs, _ = observe(scene, config, streams)
    return config, scene, obs


def mpe3d_command() -> list[str]:
    """The installed ``mpe3d`` console script, as a user runs it (falls back to
    ``python -m mpe3d.harness.cli`` when the package is not installed)."""
    script = Path(sys.executable).parent / "mpe3d"
    return [str(script)] if script.exists() else [sys.executable, "-m", "mpe3d.harness.cli"]


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

    from mpe3d.solvers.cameras import affine_cameras, exp_so3

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
