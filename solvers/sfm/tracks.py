"""Keypoint observations as flat tracks, and how far a fit is from them.

A :class:`Tracks` holds every observation t as (view k, point i, 2D point
z_t) in pixels; the helpers measure residuals ``u_k(x_i) - z_t`` of a camera
model (:mod:`.cameras`) in the units every SfM step thresholds in.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.solvers.base import Observations
from mpe3d.solvers.linalg import stacked

EXACT_RMS = 1e-12  # an RMS below this share of the image is exact: no model can do better


# Rayleigh: the median of ||r|| for isotropic Gaussian 2D residuals of std sigma.
RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))


@dataclass
class Tracks:
    """Every observation as flat arrays: its view, its point and its 2D point (pixels)."""

    view: np.ndarray  # (T,)
    point: np.ndarray  # (T,)
    z: np.ndarray  # (T, 2)
    n_points: int
    n_views: int

    @classmethod
    def from_observations(cls, obs: Observations) -> "Tracks":
        if any(v.coordinates is None for v in obs.views):
            raise MpeError("the reprojection objective needs 2D coordinates in every view "
                           "(distance matrices only allow objective='stress')")
        view, point, z = stacked(obs, [v.coordinates for v in obs.views])
        return cls(view, point, np.asarray(z, dtype=float), obs.n_points, obs.n_views)

    @functools.cached_property
    def extent(self) -> float:
        """:func:`image_size`, once per tracks (a ptp over every keypoint: 0.1 s at 600,000)."""
        return float(np.max(np.ptp(self.z, axis=0))) or 1.0

    def subset(self, rows: np.ndarray) -> "Tracks":
        return Tracks(self.view[rows], self.point[rows], self.z[rows], self.n_points, self.n_views)


def residual_lengths(X, cameras, tracks, rows=slice(None)) -> np.ndarray:
    """||u_t - z_t|| for the observations ``rows``."""
    r = cameras.project(X, tracks.view[rows], tracks.point[rows]) - tracks.z[rows]
    return np.linalg.norm(r, axis=1)


def robust_sigma(X, cameras, tracks, kept) -> float:
    """The residuals' robust scale: the median length of the ``kept`` ones over
    the Rayleigh median (what sigma isotropic Gaussian residuals would have)."""
    return sigma_of(residual_lengths(X, cameras, tracks, kept), tracks)


def sigma_of(lengths: np.ndarray, tracks) -> float:
    """:func:`robust_sigma` of residual ``lengths`` already computed."""
    # floored: keypoints are never better than 1e-5 of the image, and exact data solved
    # loosely between rounds must not make its last digits look like wrong matches
    return max(float(np.median(lengths)) / RAYLEIGH_MEDIAN, 1e-5 * image_size(tracks))


def image_size(tracks) -> float:
    """The keypoints' extent in pixels, the larger of width and height (1 if none)."""
    return tracks.extent if isinstance(tracks, Tracks) else float(np.max(np.ptp(tracks.z, axis=0))) or 1.0


def principal_point_of(tracks, given=None) -> np.ndarray:
    """The pinholes' principal point: ``given``, or the centre of the keypoints' bounding box."""
    if given is not None:
        return np.asarray(given, dtype=float)
    return (tracks.z.min(axis=0) + tracks.z.max(axis=0)) / 2


def rms(residual: np.ndarray) -> float:
    """sqrt(mean ||r_t||^2) of (T, 2) residuals."""
    return float(np.sqrt(np.mean(np.sum(residual.reshape(-1, 2) ** 2, axis=1))))
