"""Scenes and observations: config -> ground truth -> what a solver may see.

A :class:`Scene` holds the ground truth (sampled points, rotations,
visibility). :func:`observe` turns it into :class:`mpe3d.solvers.Observations`,
which hold no ground truth. Every random draw comes from its own stream of
one ``SeedSequence``, so changing the solver (or the noise) never changes the
points, the views or the visibility.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import trimesh
from scipy.spatial.distance import cdist

from mpe3d.errors import MpeError
from mpe3d.harness.scene import noise as noise_mod
from mpe3d.harness.scene import shapes, viewpoints, visibility
from mpe3d.solvers import Observations, View
from mpe3d.solvers.base import require_memory

STREAMS = ("sampling", "views", "visibility", "noise", "solver", "metrics")


def seed_streams(seed: int) -> dict[str, np.random.Generator]:
    """One independent generator per stage, all split off ``seed``."""
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    return {name: np.random.default_rng(child) for name, child in zip(STREAMS, children)}


@dataclass(frozen=True)
class Scene:
    """The ground truth of one run."""

    mesh: trimesh.Trimesh | None  # None: a plug-in dataset gave samples only
    points: np.ndarray  # (N, 3)
    rotations: np.ndarray  # (K, 3, 3)
    visible: np.ndarray  # (K, N) bool: the visibility vectors
    # seen_at_least[m - 1]: how many sampled points are visible in >= m views,
    # counted before visibility.min_views drops any
    seen_at_least: tuple[int, ...] = ()

    @property
    def projections(self) -> np.ndarray:
        return viewpoints.projections(self.rotations)

    @property
    def visible_per_view(self) -> list[int]:
        return [int(v) for v in self.visible.sum(axis=1)]


def _visibility(config: Mapping[str, Any], mesh, points, R, rng) -> np.ndarray:
    K, N = len(R), len(points)
    mode = config["visibility.mode"]
    if mode == "all":
        return visibility.all_visible(K, N)
    if mode == "exact":
        return visibility.exact(K, N, config["visibility.k"], rng)
    if mode == "count":
        kept = config["visibility.count"]
        return visibility.count(K, N, kept if kept is not None else round(0.75 * N), rng)
    if mode == "zbuffer":
        return visibility.zbuffer(points, R, config["visibility.n_rays"])
    if mesh is None:
        raise MpeError(f"shape '{config['shape']}' gives surface samples, not a mesh: "
                       "visibility.mode=raytrace needs a mesh (use zbuffer, exact, count or all)",
                       key="visibility.mode")
    return visibility.raytrace(mesh, points, R)


def build_scene(config: Mapping[str, Any], streams=None) -> Scene:
    """Sample the shape, draw the views and decide visibility.

    With ``visibility.min_views = m`` the scene keeps only the points seen in
    at least m views: they are both the ground truth and what is observed.
    """
    streams = streams or seed_streams(config["seed"])
    mesh, points = shapes.shape_samples(config["shape"], config["points"], streams["sampling"])
    if config["view_layout"] == "sphere":
        R = viewpoints.sphere_rotations(config["views"], streams["views"])
    else:
        R = viewpoints.rotations(viewpoints.draw_angles(config["views"], config["angle_range"], streams["views"]))
    alpha = _visibility(config, mesh, points, R, streams["visibility"])
    seen = alpha.sum(axis=0)
    seen_at_least = tuple(int(np.sum(seen >= m)) for m in range(1, len(R) + 1))
    m = config["visibility.min_views"]
    if m:
        keep = seen >= m
        if keep.sum() < 4:
            raise MpeError(f"visibility.min_views={m}: only {int(keep.sum())} of {len(points)} "
                           "points are seen that often; nothing to reconstruct")
        points, alpha = points[keep], alpha[:, keep]
    return Scene(mesh=mesh, points=points, rotations=R, visible=alpha, seen_at_least=seen_at_least)


def observe(scene: Scene, config: Mapping[str, Any], streams=None) -> tuple[Observations, dict]:
    """The views as a solver sees them, with the configured noise applied.

    Returns the observations and a dict of facts about the noise (for logs).
    """
    streams = streams or seed_streams(config["seed"])
    rng = streams["noise"]
    kind, q, p = config["noise.type"], config["noise.fraction"], config["noise.amplitude"]
    d = noise_mod.diameter(scene.points) if kind != "none" else 0.0
    seen = scene.points
    wrong = np.zeros_like(scene.visible)  # (K, N): where a view sees a point's wrong match
    facts = {"diameter": d}
    if kind == "correspondence":
        seen, facts["correspondences_moved"] = noise_mod.correspondence_noise(scene.points, q, p, d, rng)
        moved = np.any(seen != scene.points, axis=1)
        wrong = scene.visible & moved if config["noise.views"] == "all" \
            else noise_mod.one_view_each(moved, scene.visible, rng)
    shared = None  # noise.rows=shared: the points whose rows are noisy in every view
    if kind == "distance" and config["noise.rows"] == "shared":
        N = len(scene.points)
        shared = rng.choice(N, size=int(round(q * N)), replace=False)
    P = scene.projections
    as_coordinates = config["observe"] == "coordinates"
    largest = int(scene.visible.sum(axis=1).max())
    if not as_coordinates:
        require_memory(3 * 8 * largest ** 2, f"points={len(scene.points)}: a view's "
                       f"{largest}x{largest} distance matrix and its copies")
    out = []
    for k in range(len(P)):
        ids = np.flatnonzero(scene.visible[k])
        image = np.where(wrong[k, ids, None], seen[ids], scene.points[ids]) @ P[k].T
        if as_coordinates:  # in the view's own frame: P^k x, as an orthographic camera sees it
            out.append(View(ids=ids, coordinates=image))
            continue
        D = cdist(image, image)
        if kind == "distance":
            rows = None if shared is None else np.flatnonzero(np.isin(ids, shared))
            D = noise_mod.distance_noise(D, q, p, d, rng, rows)
        out.append(View(ids=ids, distances=D))
    empty = [k for k, v in enumerate(out) if v.size < 2]
    if empty:
        raise MpeError(f"views {empty} see fewer than 2 points; nothing to reconstruct "
                       "(raise points, or change visibility)")
    fixed = config["projections"] == "fixed"
    return Observations(n_points=len(scene.points), views=tuple(out),
                        projections=P.copy() if fixed else None), facts
