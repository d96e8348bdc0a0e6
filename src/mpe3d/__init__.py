"""mpe3d: rebuild a 3D point cloud from K ≥ 2 partial 2D views (3DMPE).

The public API, one name per job:

- :func:`reconstruct` and :func:`write_cloud`: your own views (matched 2D
  keypoints or per-view distance matrices) in, a 3D cloud out, validated;
- :func:`solve`, :class:`View` and :class:`Observations`: one solver on
  observations you built yourself (paper Eq. 1, fixed or variable setting);
- :func:`make_config` and :func:`run`: one experiment of the harness (a scene
  made from a mesh, observed, solved and scored against its ground truth);
- :func:`load_sweep`: a YAML sweep file expanded into its run configs;
- :class:`Tracker`: runs tracked in MLflow, e.g. as a pandas DataFrame;
- :func:`register_solver`, :func:`register_dataset` and :func:`register_sfm`
  (with :class:`SfmPose` and :class:`SfmResult`): plug-ins of your own.

Bad input raises :class:`mpe3d.errors.MpeError` (a ``ValueError``) with a
one-line message. The subpackages are :mod:`mpe3d.solvers` (one module per
method), :mod:`mpe3d.harness`, :mod:`mpe3d.reports` and :mod:`mpe3d.sweeps`.

Names are imported on first use, so ``import mpe3d`` (and the command line)
does not pay for MLflow, scikit-learn or trimesh until they are needed.
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:  # one source of truth: pyproject.toml
    __version__ = version("mpe3d")
except PackageNotFoundError:  # running from a checkout that was never installed
    __version__ = "0+unknown"

_PUBLIC = {
    "reconstruct": "mpe3d.harness.userdata.reconstruct",
    "write_cloud": "mpe3d.harness.userdata.formats",
    "solve": "mpe3d.solvers",
    "View": "mpe3d.solvers",
    "Observations": "mpe3d.solvers",
    "run": "mpe3d.harness.experiment.execute",
    "make_config": "mpe3d.harness.experiment.config",
    "load_sweep": "mpe3d.harness.experiment.sweep",
    "Tracker": "mpe3d.harness.tracking.store",
    "register_solver": "mpe3d.solvers",
    "Interval": "mpe3d.options",
    "Choice": "mpe3d.options",
    "Reconstruction": "mpe3d.solvers",
    "register_dataset": "mpe3d.harness.scene.shapes",
    "register_sfm": "mpe3d.solvers.sfm.methods",
    "SfmPose": "mpe3d.solvers.sfm.methods",
    "SfmResult": "mpe3d.solvers.sfm.methods",
}

__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(import_module(_PUBLIC[name]), name)
        globals()[name] = value  # later lookups skip this hook
        return value
    raise AttributeError(f"module 'mpe3d' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
