"""Visibility: which points each view sees (the paper's visibility vectors alpha^k)."""

from __future__ import annotations

import numpy as np
import trimesh

# Rays start this far (in units of the unit bounding-box diagonal) towards the
# camera, so a point does not hit the face it was sampled on; embree works in
# float32, so this must be well above 1e-7.
SELF_HIT_TOLERANCE = 1e-4
# z-buffer: a ray takes the points within this many grid spacings of its line
# (the authors' code); n_rays = points // ZBUFFER_DIVISOR rays a side by default.
ZBUFFER_RADIUS = 2.0
ZBUFFER_DIVISOR = 3


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


def zbuffer(points: np.ndarray, rotations: np.ndarray, n_rays: int | None = None) -> np.ndarray:
    """The authors' visibility on the points themselves (an orthographic z-buffer).

    Each view k lays an ``n_rays`` x ``n_rays`` grid of rays over the bounding
    box of its projected points R^k[:2] x, looking along +z of the rotated
    frame as in :func:`raytrace`. A ray takes the points within
    ``ZBUFFER_RADIUS`` grid spacings of its line (measured in spacings along
    each image axis) and keeps the nearest to the camera (the least R^k[2] x);
    a point is visible when some ray keeps it. ``n_rays`` defaults to
    N // ``ZBUFFER_DIVISOR``; the authors' README uses 400.
    """
    n_rays = max(len(points) // ZBUFFER_DIVISOR, 2) if n_rays is None else n_rays
    alpha = np.zeros((len(rotations), len(points)), dtype=bool)
    for k, R in enumerate(rotations):
        alpha[k, _nearest_along_rays(points @ R[:2].T, points @ R[2], n_rays)] = True
    return alpha


def _nearest_along_rays(image: np.ndarray, depth: np.ndarray, n_rays: int) -> np.ndarray:
    """The indices of the points that some ray of the grid keeps."""
    low, high = image.min(axis=0), image.max(axis=0)
    spacing = np.where(high > low, (high - low) / (n_rays - 1), 1.0)
    cell = (image - low) / spacing  # in grid spacings: the rays sit at the integers
    reach = np.arange(-int(ZBUFFER_RADIUS), int(ZBUFFER_RADIUS) + 2)
    grid = np.stack(np.meshgrid(reach, reach, indexing="ij"), axis=-1).reshape(-1, 2)
    rays = np.floor(cell)[:, None] + grid[None]  # (N, r, 2): the nodes round each point
    near = np.all((rays >= 0) & (rays <= n_rays - 1), axis=2) \
        & (np.linalg.norm(rays - cell[:, None], axis=2) <= ZBUFFER_RADIUS)
    point = np.broadcast_to(np.arange(len(image))[:, None], near.shape)[near]
    ray = (rays[..., 0] * n_rays + rays[..., 1])[near].astype(np.int64)
    order = np.lexsort((depth[point], ray))  # by ray, nearest first
    first = np.concatenate([[True], ray[order][1:] != ray[order][:-1]])
    return np.unique(point[order][first])
