"""The cameras' start and each camera model's fit: the weak-perspective
(affine) start, the race of focal-length starts that a pinhole fit begins
with (on at most RACE_POINTS evenly spread points), and the orthographic,
perspective and radial fits from the scaled one."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mpe3d.solvers.factorize import affine_als, metric_upgrade_pd
from mpe3d.solvers.linalg import elongation
from mpe3d.solvers.sfm.adjust import Fit, LMOptions, adjust
from mpe3d.solvers.sfm.cameras import (
    Cameras,
    affine_cameras,
    with_distortion,
)
from mpe3d.solvers.sfm.support import ELONGATION, mean_by_view, placed_points, weak_points
from mpe3d.solvers.sfm.tracks import Tracks, image_size, principal_point_of, rms
from mpe3d.solvers.sfm.triangulation import adjusted_points, dlt_rows, least_squares_points
from mpe3d.solvers.stress import project_rows

# Focal lengths tried from the weak-perspective start, in units of the image size.
# (Shorter ones put the cloud behind the camera: a half-image-wide object at
# depth f / s.)
_FOCAL_STARTS = (1.0, 2.0, 4.0)
_SCOUT = 8  # iterations from each start before the best is chosen, at most
_RACE = (2, 4, _SCOUT)  # the stages of that race (iterations done after each)
_RACE_RATIO = 2.0  # a start this many times the best's RMS after a stage is dropped
# points a race is run on, at most: enough to rank starts 2x apart, and the
# race's iterations then cost what 1,000 points cost, however many there are
RACE_POINTS = 1000



class WeakStart(NamedTuple):
    """The weak-perspective start: points, orthonormal rows, scales, translations,
    and the RMS of the affine fit under it."""

    X: np.ndarray
    P: np.ndarray  # (K, 2, 3)
    scale: np.ndarray  # (K,)
    t: np.ndarray  # (K, 2)
    affine_rms: float


def weak_perspective_start(tracks: Tracks, sweeps: int = 20, tol: float = 1e-10) -> WeakStart:
    """X, orthonormal rows P (K, 2, 3), scales s and translations t from the
    affine factorisation (``sweeps`` alternating sweeps after it is grown) and
    the positive-definite upgrade, and the RMS of the affine fit."""
    X, L, _, _ = affine_als(tracks.view, tracks.point, tracks.z, tracks.n_points,
                            tracks.n_views, sweeps, tol)
    t = _translations(X, L, tracks)
    affine = np.einsum("tab,ta->tb", L[tracks.view], X[tracks.point]) + t[tracks.view] - tracks.z
    A = metric_upgrade_pd(L)
    X = X @ np.linalg.inv(A).T
    rows = np.einsum("ia,kib->kba", A, L)  # (K, 2, 3): s_k times orthonormal rows
    scale = np.sqrt(np.sum(rows ** 2, axis=(1, 2)) / 2)
    norm = np.exp(np.mean(np.log(scale)))  # the cloud in pixels at the mean scale
    X, scale = X * norm, scale / norm
    X = X - X.mean(axis=0)
    P = project_rows(rows)
    t = _translations_for(X, P, scale, tracks)
    return WeakStart(X, P, scale, t, rms(affine))


def scaled_fit(tracks, lm: LMOptions, grown=None):
    """The scaled fit from two affine starts, barely polished and after some
    sweeps, and from the ``grown`` (X, cameras) of :mod:`.incremental`. Which
    one reaches the lowest minimum depends on the tracks, so each is scouted
    for a few iterations and the best one solved to the end."""
    starts = []
    for sweeps in (1, 20):
        X, P, scale, t, affine_rms = weak_perspective_start(tracks, sweeps, lm.tol)
        starts.append(((X, affine_cameras("scaled", P, scale, t)), affine_rms))
    if grown is not None:
        starts.append((grown, affine_rms))
    return _best_of(starts, tracks, lm)


def _best_of(starts, tracks, lm: LMOptions):
    """Scout the ((X, cameras), extra) starts in a race, then solve the lowest
    to the end; returns its :class:`~.adjust.Fit` and its extra.

    Each start runs to the iteration counts of ``_RACE`` in turn; after each
    stage the starts whose RMS exceeds ``_RACE_RATIO`` times the best's are
    dropped, and the race ends when one is left (or at ``_SCOUT`` iterations).
    A start that far behind after two iterations has not won on any tracks we
    have (the mirror images of a pinhole start sit 4-7x above after two), and
    every iteration here costs a full reduced camera system: the six pinhole
    starts' 48 scouting iterations were 17 s of 55 on 250 cameras x 3,000
    points. Scouts stop at a relative decrease of ``ROUND_TOL``: the race
    only ranks them. Over ``RACE_POINTS`` placed points the race runs on
    that many of them, evenly spread (:func:`race_points`), and the others are
    placed for the winner's cameras before its solve on all: a 2x lead shows
    on 1,000 points as on 3,000, at a third of the cost an iteration (250
    cameras x 3,000 points: 37 -> 31 s, the same final RMS to 15 digits).
    """
    scout = lm.loose()
    racing = [(Fit(*start, np.empty(0), False), extra) for start, extra in starts]
    raced = race_points(tracks)
    race_tracks = tracks if raced is None else tracks.subset(raced[tracks.point])
    done = 0
    for stage in _RACE:
        budget = min(stage, lm.max_iter) - done
        if budget <= 0:
            break
        racing = [(_continued(fit, race_tracks, scout.short(budget)), extra)
                  for fit, extra in racing]
        done += budget
        best = min(fit.history[-1] for fit, _ in racing)
        racing = [(fit, extra) for fit, extra in racing if fit.history[-1] <= _RACE_RATIO * best]
        if len(racing) == 1:
            break
    scouting, extra = min(racing, key=lambda f: f[0].history[-1])
    if raced is not None and len(scouting.history) > 1:  # cameras moved: the points left
        # out of the race placed for the cameras it reached
        scouting = scouting._replace(X=adjusted_points(scouting.X, scouting.cameras, tracks,
                                                       placed_points(tracks, slice(None)) & ~raced))
    # the winner solved to the end without its points of weak geometry (see peel_outliers)
    weak = weak_points(scouting, tracks, np.ones(len(tracks.view), dtype=bool))[0]
    fit = _continued(scouting._replace(converged=False), tracks.subset(~weak[tracks.point]), lm)
    if weak.any():
        fit = fit._replace(X=adjusted_points(fit.X, fit.cameras, tracks, weak))
    return fit, extra


def race_points(tracks) -> np.ndarray | None:
    """(N,) bool: the placed points a race of starts is run on, RACE_POINTS
    of them evenly spread over the point indices; None when there are no more
    than that (the race runs on all)."""
    ids = np.flatnonzero(placed_points(tracks, slice(None)))
    if len(ids) <= RACE_POINTS:
        return None
    raced = np.zeros(tracks.n_points, dtype=bool)
    raced[ids[np.linspace(0, len(ids) - 1, RACE_POINTS).round().astype(int)]] = True
    return raced


def _continued(fit, tracks, lm: LMOptions):
    """``fit`` solved on from where it stands (unless it converged), its history kept."""
    if fit.converged:
        return fit
    more = adjust(fit.X, fit.cameras, tracks, lm)
    return more._replace(history=np.concatenate([fit.history, more.history[1:] if len(fit.history)
                                                 else more.history]))


def _orthographic(X, scaled: Cameras, tracks, principal_point, shared_focal, lm: LMOptions, focal=None):
    """From the scaled solution: one scale for all views, folded into the cloud."""
    s = scaled.scale()
    common = float(np.exp(np.mean(np.log(s))))
    R = scaled.current_rotations()
    start = affine_cameras("orthographic", R[:, :2], np.ones(len(s)), scaled.params[:, 3:5])
    return adjust(X * common, start, tracks, lm)


def _perspective(X, scaled: Cameras, tracks, principal_point, shared_focal, lm: LMOptions, focal=None):
    """From the scaled solution, at several focal lengths (and at the prior
    ``focal`` in pixels, when one is known) and in both depth orders (weak
    perspective cannot tell a cloud from its mirror image in depth; a pinhole
    can): a short solve from each, then the best one to the end."""
    c = principal_point_of(tracks, principal_point)
    size = image_size(tracks)
    R, s, t = scaled.current_rotations(), scaled.scale(), scaled.params[:, 3:5]
    centre = X.mean(axis=0)  # the pinhole matches the weak perspective at the centroid
    X, t = X - centre, t + s[:, None] * (R[:, :2] @ centre)
    X = _bounded_depth(X)
    starts = []
    focals = ([] if focal is None else [float(focal)]) + [factor * size for factor in _FOCAL_STARTS]
    for mirror in (1.0, -1.0):  # -X seen through -R[:2] gives the same weak-perspective images
        for f in focals:
            cameras = affine_cameras("perspective", mirror * R[:, :2], s, t, focal=f,
                                     principal_point=c, shared_focal=shared_focal)
            starts.append(((_in_front(mirror * X, cameras, tracks), cameras), None))
    return _best_of(starts, tracks, lm)[0]


def grown_pinhole(tracks, principal_point, lm: LMOptions, focal=None, seed: int = 0):
    """The perspective fit from the start grown view by view
    (:mod:`.pinhole_start`), adjusted to the end over the observations it
    kept; its (K,) registered views and those (T,) observations. None when no
    pair of views starts it."""
    from mpe3d.solvers.sfm.pinhole_start import pinhole_start

    c = principal_point_of(tracks, principal_point)
    start = pinhole_start(tracks, c, focal, seed)
    if start is None:
        return None
    fit = adjust(start.X, start.cameras, tracks.subset(start.kept), lm)
    X, placed = _the_rest_placed(fit, tracks, start)
    # what the fit rests on: the observations the start kept, and those of the
    # points it left out only for their narrow rays; the rest are suspects
    rows = start.registered[tracks.view] & (start.kept | (placed & ~start.placed)[tracks.point])
    return fit._replace(X=X), start.registered, rows


def _the_rest_placed(fit, tracks, start):
    """The points the start left unplaced for their narrow rays alone, placed by
    linear triangulation under the fit's cameras (the weak-geometry rule decides
    them later), where every camera sees them in front; and (N,) which points
    now have a place."""
    X, N = fit.X.copy(), tracks.n_points
    rows = start.registered[tracks.view]
    todo = start.narrow & (np.bincount(tracks.point[rows], minlength=N) >= 2)
    rows &= todo[tracks.point]
    if not rows.any():
        return X, start.placed.copy()
    A, b = dlt_rows(fit.cameras.projection_matrices(), tracks.view[rows], tracks.z[rows])
    X[todo] = least_squares_points(A, b, tracks.point[rows], N)[todo]
    seen = np.all(np.isfinite(fit.cameras.project(X, tracks.view[rows], tracks.point[rows])), axis=1)
    unseen = np.zeros(N, dtype=bool)
    unseen[tracks.point[rows][~seen]] = True
    # the algebraic error's place is a pinhole's start, not its optimum: each point
    # is adjusted alone under the fit's cameras
    X = adjusted_points(X, fit.cameras, tracks.subset(rows), todo & ~unseen)
    return X, start.placed | (todo & ~unseen)


def _radial(X, pinhole: Cameras, tracks, principal_point, shared_focal, lm: LMOptions, focal=None):
    """From the pinhole's solution, with k1 = k2 = 0: a lens's distortion is a
    small change of a pinhole's images, so its optimum is near."""
    return adjust(X, with_distortion(pinhole), tracks, lm)


FITTERS = {"orthographic": _orthographic, "perspective": _perspective, "radial": _radial}


def _in_front(X: np.ndarray, cameras: Cameras, tracks: Tracks, keep: float = 0.5) -> np.ndarray:
    """X with each point that some view of it would see behind its pinhole pulled
    towards the centroid (which every camera sees at depth f / s) until it stands
    at ``keep`` times that depth or more: one such point would make the whole
    start's cost infinite. Long sequences round an object (COLMAP's tracks of
    250 photos) hold a few two-view points far out in depth."""
    R = cameras.current_rotations()
    toward = np.einsum("ti,ti->t", R[tracks.view, 2], X[tracks.point])  # X is centred
    depth = cameras.params[tracks.view, 5]
    behind = toward < (keep - 1.0) * depth  # depth + toward < keep * depth
    if not behind.any():
        return X
    alpha = np.ones(len(X))
    np.minimum.at(alpha, tracks.point[behind], (1.0 - keep) * depth[behind] / -toward[behind])
    return X * alpha[:, None]


def _bounded_depth(X: np.ndarray, limit: float = ELONGATION) -> np.ndarray:
    """X with a run-away principal axis pulled in to the second one's extent: a
    start from which no point lies behind a pinhole camera."""
    if elongation(X) <= limit:
        return X
    centred = X - X.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]
    coords = centred @ axes.T
    extents = np.ptp(coords, axis=0)
    coords[:, 0] *= extents[1] / extents[0]
    return coords @ axes + X.mean(axis=0)


def _translations(X, L, tracks):
    """The per-view 2D translations that best fit z_t ~ L_k^T x_i + t_k."""
    pred = np.einsum("tab,ta->tb", L[tracks.view], X[tracks.point])
    return mean_by_view(tracks.z - pred, tracks)


def _translations_for(X, P, scale, tracks):
    pred = scale[tracks.view, None] * np.einsum("tab,tb->ta", P[tracks.view], X[tracks.point])
    return mean_by_view(tracks.z - pred, tracks)

