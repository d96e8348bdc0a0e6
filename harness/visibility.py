"""Visibility: which points each view sees (the paper's visibility vectors alpha^k)."""

from __future__ import annotations

import numpy as np
import trimesh

# Rays start this far (in units of the unit bounding-box diagonal) towards the
# camera, so a point does not hit the face it was sampled on; embree works in
# float32, so this must be well above 1e-7.
SELF_HIT_TOLERANCE = 1e-4


def all_visible(n_views: int, n_points: int) -> np.ndarray:
    return np.ones((n_views, n_points), dtype=bool)


def exact(n_views: int, n_points: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """Every point visible in exactly ``k`` views, the views chosen uniformly."""
    order = np.argsort(rng.random((n_points, n_views)), axis=1)[:, :k]
    alpha = np.zeros((n_views, n_points), dtype=bool)
    alpha[order.T, np.arange(n_points)[None, :]] = True
    return alpha


def count(n_views: int, n_points: int, kept: int, rng: np.random.Generator) -> np.ndarray:
    """Every view keeps ``kept`` points chosen uniformly (the paper's theta)."""
    alpha = np.zeros((n_views, n_points), dtype=bool)
    for k in range(n_views):
        alpha[k, rng.choice(n_points, size=kept, replace=False)] = True
    return alpha


def raytrace(mesh: trimesh.Trimesh, points: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """A point is visible in view k when the ray from it towards that view's camera
    hits no part of the mesh.

    The camera of view k looks along +z of the rotated frame (paper, Section
    "Datasets and Experimental Setup"), so the ray towards it runs along
    -R^k[2] in world coordinates. Orthographic, like the projections.
    """
    alpha = np.zeros((len(rotations), len(points)), dtype=bool)
    for k, R in enumerate(rotations):
        towards_camera = np.broadcast_to(-R[2], points.shape)
        origins = points + SELF_HIT_TOLERANCE * towards_camera
        alpha[k] = ~mesh.ray.intersects_any(origins, towards_camera)
    return alpha
