"""Shapes: bundled stand-in meshes, mesh files, ShapeNet/Pix3D ids, procedural solids.

Every mesh is centred on its bounding-box centre and scaled to unit
bounding-box diagonal (the ShapeNet convention) before sampling.
"""

from __future__ import annotations

import json
import os
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
import trimesh

from mpe3d.errors import MpeError, suggest

PROCEDURAL = ("torus", "box", "sphere", "cone")
MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def _assets() -> Path:
    return Path(str(resources.files(__package__) / "assets" / "meshes"))


@lru_cache(maxsize=1)
def bundled_manifest() -> dict[str, dict]:
    """Bundled mesh name -> its manifest entry (source, creator, paper category)."""
    entries = json.loads((_assets() / "manifest.json").read_text())
    return {e["name"]: e for e in entries}


def shape_names() -> list[str]:
    """Every name ``shape`` accepts without a path: bundled and procedural."""
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


def check_shape(spec: str) -> None:
    """Fail early, without loading anything, if ``spec`` names no shape or no file."""
    path = _mesh_path(spec)
    if path is not None and not path.is_file():
        raise MpeError(f"shape '{spec}': no mesh file at {path}", key="shape")


def load_shape(spec: str) -> trimesh.Trimesh:
    """The normalised mesh for a ``shape`` value (see module doc)."""
    path = _mesh_path(spec)
    mesh = _procedural(spec) if path is None else _read_mesh(path, spec)
    return normalise(mesh)


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
