"""Shapes: bundled stand-in meshes, mesh files, ShapeNet/Pix3D ids, procedural
solids, and plug-in datasets (``shape=NAME:item``, see :func:`register_dataset`).

Every mesh, and a dataset's own samples, is centred on its bounding-box
centre and scaled to unit bounding-box diagonal (the ShapeNet convention).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from mpe3d import plugins
from mpe3d.errors import MpeError, suggest

PROCEDURAL = ("torus", "box", "sphere", "cone")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")
DATASET_ROOTS = ("shapenet", "pix3d")  # ours: shapenet:<synset>/<id>, pix3d:<category>/<model>


@dataclass(frozen=True)
class DatasetSpec:
    """A registered shape source: ``func(item, *, n_points, random_state)``
    returns ``n_points`` surface samples ``(n_points, 3)`` or a mesh."""

    name: str
    func: Callable
    items: tuple[str, ...]
    summary: str
    origin: plugins.Origin | None = None


DATASETS: dict[str, DatasetSpec] = {}
plugins.add_registry("dataset", DATASETS)


def register_dataset(name: str, *, items: tuple[str, ...] = (), summary: str = ""):
    """Register the decorated function as dataset ``name`` (a decorator), used
    as ``shape=NAME:item`` (or ``shape=NAME`` when it lists no items).

    The function is ``func(item, *, n_points, random_state)``: ``item`` is the
    part after the colon, ``random_state`` a ``numpy.random.Generator`` (the
    run's sampling stream). It returns either ``n_points`` surface samples as
    an ``(n_points, 3)`` array, or a ``trimesh.Trimesh`` that mpe3d samples as
    it samples its own meshes (ray-traced visibility and photos need a mesh).

    Parameters
    ----------
    name : str
        Letters, digits, ``_`` and ``-``; not a bundled, procedural or
        ``shapenet``/``pix3d`` name.
    items : tuple of str, default ()
        The items it offers (``mpe3d shapes`` lists them); empty: any item.
    summary : str, default ""
        One line for ``mpe3d shapes``.
    """
    if not name or not all(c.isalnum() or c in "_-" for c in name):
        raise TypeError(f"dataset {name!r}: use letters, digits, '_' and '-' only")
    if name in (*DATASET_ROOTS, *PROCEDURAL) or name in bundled_manifest():
        raise TypeError(f"dataset {name!r}: the name of one of mpe3d's own shapes")

    def decorator(func):
        origin = plugins.claim("dataset", name, func)
        DATASETS[name] = DatasetSpec(name, func, tuple(items), summary, origin)
        return func
    return decorator


def _dataset(spec: str) -> tuple[DatasetSpec, str] | None:
    """The plug-in dataset ``spec`` names, with its item (``None``: not a dataset)."""
    name, colon, item = spec.partition(":")
    if name in DATASET_ROOTS or name in PROCEDURAL or name in bundled_manifest() or os.sep in name:
        return None
    if name not in DATASETS:
        plugins.load_entry_points()
    if name not in DATASETS:
        if colon:
            raise MpeError(f"shape '{spec}': no dataset '{name}' (datasets: "
                           f"{', '.join(sorted(DATASETS)) or 'none; add one with a plug-in'})"
                           + plugins.failure_note("dataset"), key="shape", hint=suggest(name, DATASETS))
        return None
    dataset = DATASETS[name]
    if dataset.items and item not in dataset.items:
        raise MpeError(f"shape '{spec}': dataset '{name}' has no item '{item}' (items: "
                       f"{', '.join(dataset.items)})", key="shape", hint=suggest(item, dataset.items))
    return dataset, item


def shape_samples(spec: str, count: int, rng: np.random.Generator) -> tuple[trimesh.Trimesh | None, np.ndarray]:
    """The normalised mesh of ``spec`` (``None`` for a dataset that gives
    samples only) and ``count`` surface samples of it."""
    found = _dataset(spec)
    if found is None:
        mesh = load_shape(spec)
        return mesh, sample_points(mesh, count, rng)
    dataset, item = found
    out = dataset.func(item, n_points=count, random_state=rng)
    if isinstance(out, trimesh.Trimesh):
        mesh = normalise(out)
        return mesh, sample_points(mesh, count, rng)
    points = np.asarray(out, dtype=np.float64)
    if points.shape != (count, 3) or not np.all(np.isfinite(points)):
        raise MpeError(f"shape '{spec}': dataset '{dataset.name}' ({dataset.origin}) gave "
                       f"{'non-finite ' if points.shape == (count, 3) else ''}samples of shape "
                       f"{points.shape}, expected ({count}, 3) finite values or a trimesh.Trimesh")
    return None, normalise_points(points)


def normalise_points(points: np.ndarray) -> np.ndarray:
    """Samples centred on their bounding-box centre, scaled to unit diagonal."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diagonal) or diagonal <= 0:
        raise MpeError("shape: the samples are degenerate (zero-size bounding box)")
    return (points - (lo + hi) / 2.0) / diagonal


def _assets() -> Path:
    return Path(str(resources.files(__package__) / "assets" / "meshes"))


@lru_cache(maxsize=1)
def bundled_manifest() -> dict[str, dict]:
    """Bundled mesh name -> its manifest entry (source, creator, paper category)."""
    entries = json.loads((_assets() / "manifest.json").read_text())
    return {e["name"]: e for e in entries}


def shape_names() -> list[str]:
    """Every name ``shape`` accepts without a path: bundled and procedural
    (plug-in datasets, ``NAME:item``, are in :data:`DATASETS`)."""
    return sorted(bundled_manifest()) + list(PROCEDURAL)


def _procedural(name: str) -> trimesh.Trimesh:
    if name == "torus":
        return trimesh.creation.torus(major_radius=1.0, minor_radius=0.35,
                                      major_sections=64, minor_sections=32)
    if name == "box":
        return trimesh.creation.box(extents=(1.0, 0.7, 0.4))
    if name == "sphere":
        return trimesh.creation.icosphere(subdivisions=4)
    return trimesh.creation.cone(radius=0.5, height=1.0, sections=64)


def _dataset_path(spec: str) -> Path:
    kind, _, rest = spec.partition(":")
    env = {"shapenet": "SHAPENET_DIR", "pix3d": "PIX3D_DIR"}[kind]
    root = os.environ.get(env)
    if not root:
        raise MpeError(f"shape '{spec}': set ${env} to the {kind} dataset root", key="shape")
    parts = rest.strip("/").split("/")
    if len(parts) != 2 or not all(parts):
        form = "shapenet:<synset>/<model_id>" if kind == "shapenet" else "pix3d:<category>/<model>"
        raise MpeError(f"shape '{spec}': expected {form}", key="shape")
    if kind == "shapenet":  # ShapeNetCore.v2 layout
        return Path(root) / parts[0] / parts[1] / "models" / "model_normalized.obj"
    return Path(root) / "model" / parts[0] / parts[1] / "model.obj"  # Pix3D layout


def _read_mesh(path: Path, label: str) -> trimesh.Trimesh:
    if not path.is_file():
        raise MpeError(f"shape '{label}': no mesh file at {path}")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise MpeError(f"shape '{label}': cannot read {path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MpeError(f"shape '{label}': {path} holds no triangles")
    return mesh


def _mesh_path(spec: str) -> Path | None:
    """Where the mesh for ``spec`` lives (``None`` for procedural solids)."""
    if spec in PROCEDURAL:
        return None
    if spec in bundled_manifest():
        return _assets() / f"{spec}.ply"
    if spec.startswith(("shapenet:", "pix3d:")):
        return _dataset_path(spec)
    if Path(spec).suffix.lower() in MESH_SUFFIXES or os.sep in spec:
        return Path(spec).expanduser()
    raise MpeError(f"shape: unknown shape '{spec}' (use one of {', '.join(shape_names())} "
                   "or a mesh file path)", key="shape", hint=suggest(spec, shape_names()))


def mesh_file(spec: str) -> Path | None:
    """The mesh file a ``shape`` value reads (None: a procedural solid or a
    plug-in's data set, made by code)."""
    if _dataset(spec) is not None:
        return None
    return _mesh_path(spec)


def check_shape(spec: str) -> None:
    """Fail early, without loading anything, if ``spec`` names no shape or no file."""
    if _dataset(spec) is not None:
        return
    path = _mesh_path(spec)
    if path is not None and not path.is_file():
        raise MpeError(f"shape '{spec}': no mesh file at {path}", key="shape")


def load_shape(spec: str) -> trimesh.Trimesh:
    """The normalised mesh for a ``shape`` value (see module doc)."""
    if _dataset(spec) is not None:
        raise MpeError(f"shape '{spec}': a plug-in dataset gives samples per run, not one mesh "
                       "(pipeline=colmap renders a mesh: use a bundled shape or a mesh file)", key="shape")
    path = _mesh_path(spec)
    if path is None or spec in bundled_manifest():
        return _packaged_shape(spec, path).copy()
    return normalise(_read_mesh(path, spec))


@lru_cache(maxsize=16)
def _packaged_shape(spec: str, path: Path | None) -> trimesh.Trimesh:
    """A bundled or procedural shape, normalised once per process: a sweep's
    worker reads the same few meshes for hundreds of runs (5 ms a read; the
    copy the caller gets, 0.4 ms). A user's mesh file is read every time, as
    it may change between runs."""
    return normalise(_procedural(spec) if path is None else _read_mesh(path, spec))


def normalise(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre on the bounding-box centre and scale to unit bounding-box diagonal."""
    mesh = mesh.copy()
    lo, hi = mesh.bounds
    diagonal = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diagonal) or diagonal <= 0:
        raise MpeError("shape: the mesh is degenerate (zero-size bounding box)")
    mesh.apply_translation(-(lo + hi) / 2.0)
    mesh.apply_scale(1.0 / diagonal)
    return mesh


def sample_points(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` area-uniform samples on the surface, float64 ``(count, 3)``."""
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return np.asarray(points, dtype=np.float64)
