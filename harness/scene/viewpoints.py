"""Views: the paper's Eq. 9 rotations with angles drawn from binned sub-ranges,
or directions spread evenly over the sphere."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def rotation(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """Eq. 9: R = R_z(alpha) R_y(beta) R_x(gamma), angles in radians.

    The paper prints -sin(alpha) in the bottom-left corner; that matrix is not
    orthonormal. The product R_z R_y R_x it is written from has -sin(beta)
    there, which is what we use.
    """
    ca, sa = np.cos(alpha), np.sin(alpha)
    cb, sb = np.cos(beta), np.sin(beta)
    cg, sg = np.cos(gamma), np.sin(gamma)
    return np.array([
        [ca * cb, ca * sb * sg - sa * cg, ca * sb * cg + sa * sg],
        [sa * cb, sa * sb * sg + ca * cg, sa * sb * cg - ca * sg],
        [-sb, cb * sg, cb * cg],
    ])


def angle_bins(n_views: int, angle_range: float) -> np.ndarray:
    """The ``(K, 2)`` sub-ranges, in degrees, that view k's angles are drawn from.

    For k <= K/2 the bin is [(k-1) theta_r / K, k theta_r / K]; the views past
    K/2 take the same bins negated. For odd K the bins of K + 1 are built and
    the last is dropped.
    """
    K = n_views + (n_views % 2)
    half = K // 2
    width = angle_range / K
    positive = np.array([[(k - 1) * width, k * width] for k in range(1, half + 1)])
    bins = np.vstack([positive, -positive])
    return bins[:n_views]


def draw_angles(n_views: int, angle_range: float, rng: np.random.Generator) -> np.ndarray:
    """``(K, 3)`` angles (alpha, beta, gamma) in degrees, each uniform in its view's bin."""
    bins = angle_bins(n_views, angle_range)
    u = rng.uniform(size=(n_views, 3))
    return bins[:, :1] + u * (bins[:, 1:] - bins[:, :1])


def rotations(angles_deg: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` rotations from ``(K, 3)`` angles in degrees."""
    return np.stack([rotation(*np.radians(a)) for a in angles_deg])


def projections(R: np.ndarray) -> np.ndarray:
    """Orthographic projections P^k: the first two rows of each R^k."""
    return R[:, :2, :].copy()


def sphere_rotations(n_views: int, rng: np.random.Generator) -> np.ndarray:
    """``(K, 3, 3)`` rotations whose cameras look from K nearly equidistant directions.

    The directions are a Fibonacci lattice on the sphere (the paper's
    "equidistant views" for its raytrace-count figure), turned as a whole by a
    uniformly random rotation, each camera with a random roll. Row 2 of R^k is
    minus the direction towards camera k, as in :func:`mpe3d.harness.scene.visibility.raytrace`.
    """
    k = np.arange(n_views)
    z = 1.0 - (2.0 * k + 1.0) / n_views
    r = np.sqrt(1.0 - z ** 2)
    towards = np.column_stack([r * np.cos(k * GOLDEN_ANGLE), r * np.sin(k * GOLDEN_ANGLE), z])
    towards = Rotation.random(random_state=rng).apply(towards)
    out = np.empty((n_views, 3, 3))
    for i, d in enumerate(towards):
        helper = np.eye(3)[np.argmin(np.abs(d))]  # any axis not parallel to d
        u = np.cross(d, helper)
        u /= np.linalg.norm(u)
        v = np.cross(-d, u)
        roll = rng.uniform(0.0, 2.0 * np.pi)
        first = np.cos(roll) * u + np.sin(roll) * v
        second = np.cross(-d, first)
        out[i] = np.stack([first, second, -d])
    return out
