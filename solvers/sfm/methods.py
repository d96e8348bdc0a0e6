"""Structure-from-motion methods of your own: the plug-in kind ``sfm``.

A plug-in SfM method is a function ``fn(views, *, random_state) -> SfmResult``
registered with :func:`register_sfm`. It is given the photos' tracks (each
photo's keypoints and their track ids, its size, its EXIF focal length if
any, and which physical camera took it) and returns the photos it registered
(a pose, a focal length and a principal point each) and the 3D points it
placed. That is what mpe3d's own methods (:data:`BUILT_IN`) see of a photo
set too, so a plug-in runs wherever they do: ``mpe3d check-solver NAME``
checks it, and a ``pipeline=photos`` sweep scores it by pose AUC beside them.

:func:`run_sfm` calls one and checks its output at the boundary, so that a
bad pose or a NaN is one line naming the plug-in and the field, not a
traceback in the scoring. This module imports only numpy,
:mod:`mpe3d.errors` and :mod:`mpe3d.plugins`: a plug-in registering here
pulls in none of the SfM stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from mpe3d import plugins
from mpe3d.errors import MpeError, suggest
from mpe3d.plugins import Origin

BUILT_IN = ("bundle", "colmap", "colmap_global")  # mpe3d's own SfM methods: no plug-in takes these names
ORTHONORMAL = 1e-6  # |R R^T - I| and |det R - 1| at most


@dataclass(frozen=True)
class SfmView:
    """One photo, as a method is given it."""

    name: str  # the photo's file name
    ids: np.ndarray  # (n,) int64 track ids of its keypoints
    xy: np.ndarray  # (n, 2) keypoints in the photo's own pixels (origin at the top-left corner)
    image_size: tuple[int, int]  # (width, height) in pixels
    focal_px: float | None  # a plausible EXIF focal length in pixels (one camera for all photos), else None
    camera: int  # which physical camera took it (photos with the same number share intrinsics)


@dataclass(frozen=True)
class SfmPose:
    """One registered photo, as a method returns it: ``x_cam = R x + t``
    (COLMAP's convention), a pinhole of square pixels."""

    rotation: np.ndarray  # (3, 3) world -> camera, orthonormal, det +1
    translation: np.ndarray  # (3,)
    focal_px: float
    principal_point: tuple[float, float]  # pixels


@dataclass
class SfmResult:
    """What a method returns: the photos it registered, and the points it placed."""

    poses: dict[str, SfmPose]  # registered photos only, by name
    point_ids: np.ndarray  # (M,) the track ids it placed
    points: np.ndarray  # (M, 3)
    termination: str = ""  # why it stopped, in words


@dataclass(frozen=True)
class SfmMethod:
    """A registered SfM plug-in: its name, function, one-line summary and plug-in."""

    name: str
    func: Callable[..., SfmResult]
    summary: str
    origin: Origin | None = None


SFM_METHODS: dict[str, SfmMethod] = {}  # plug-in SfM methods only; ours are BUILT_IN
plugins.add_registry("sfm", SFM_METHODS)


def register_sfm(name: str, *, summary: str = ""):
    """Register the decorated function as the SfM method ``name`` (a decorator).

    The function is ``fn(views, *, random_state) -> SfmResult``: ``views`` is
    a list of :class:`SfmView`, and ``random_state`` an int seed (build a
    ``numpy.random.default_rng(random_state)`` from it if you draw random
    numbers: one seed must give one result).

    Parameters
    ----------
    name : str
        The name ``mpe3d check-solver`` and a photos sweep's ``--solver`` use;
        not one of :data:`BUILT_IN`, nor another plug-in's.
    summary : str, default ""
        One line for ``mpe3d solvers``.
    """
    def decorator(func):
        origin = plugins.claim("sfm", name, func, reserved=BUILT_IN)
        SFM_METHODS[name] = SfmMethod(name, func, summary, origin)
        return func
    return decorator


def get_sfm(name: str) -> SfmMethod:
    """The SfM plug-in ``name`` (installed ones are read the first time one is missing)."""
    if name not in SFM_METHODS:
        plugins.load_entry_points()
    if name in SFM_METHODS:
        return SFM_METHODS[name]
    if name in BUILT_IN:
        raise MpeError(f"'{name}' is one of mpe3d's own SfM methods, not a plug-in")
    known = ", ".join(sorted(SFM_METHODS)) or "none"
    raise MpeError(f"unknown SfM method '{name}' (plug-ins: {known})" + plugins.failure_note("sfm"),
                   key="solver", hint=suggest(name, [*SFM_METHODS, *BUILT_IN]))


def run_sfm(name: str, views: list[SfmView], random_state: int) -> SfmResult:
    """Run the SfM plug-in ``name`` on ``views`` and check what it returns.

    Raises :class:`~mpe3d.errors.MpeError` in one line naming the plug-in and
    the field when the output breaks the contract (see :class:`SfmResult`).
    """
    method = get_sfm(name)
    result = method.func(list(views), random_state=int(random_state))
    _validate(method, result, views)
    return _as_arrays(result)


def _as_arrays(result: SfmResult) -> SfmResult:
    """A validated result as the arrays its fields promise (a plug-in may return lists)."""
    poses = {photo: SfmPose(np.asarray(pose.rotation, dtype=float), np.asarray(pose.translation, dtype=float),
                            float(pose.focal_px), tuple(float(v) for v in pose.principal_point))
             for photo, pose in result.poses.items()}
    return SfmResult(poses, np.asarray(result.point_ids, dtype=np.int64).reshape(-1),
                     np.asarray(result.points, dtype=float).reshape(-1, 3), result.termination)


def _validate(method: SfmMethod, result, views: list[SfmView]) -> None:
    who = f"SfM method '{method.name}'" + (f" ({method.origin})" if method.origin else "")

    def fail(field: str, what: str):
        raise MpeError(f"{who}: {field} {what}")

    if not isinstance(result, SfmResult):
        fail("result", f"is a {type(result).__name__}; return an mpe3d SfmResult")
    if not isinstance(result.poses, dict):
        fail("poses", f"is a {type(result.poses).__name__}; expected a dict of photo name -> SfmPose")
    names = {view.name for view in views}
    for photo, pose in result.poses.items():
        _validate_pose(fail, photo, pose, names)
    ids, points = np.asarray(result.point_ids), np.asarray(result.points)
    if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
        fail("point_ids", f"has shape {ids.shape} and dtype {ids.dtype}; expected (M,) integer track ids")
    if points.shape != (len(ids), 3) or not np.issubdtype(points.dtype, np.number):
        fail("points", f"has shape {points.shape}; expected ({len(ids)}, 3), one per point id")
    if not np.all(np.isfinite(points)):
        fail("points", "hold NaN or inf")
    if len(np.unique(ids)) != len(ids):
        fail("point_ids", "list a track id twice")
    given = np.concatenate([np.asarray(view.ids) for view in views]) if views else np.zeros(0, int)
    stray = np.setdiff1d(ids, given)
    if stray.size:
        fail("point_ids", f"hold {stray.size} id(s) no photo has (e.g. {int(stray[0])})")
    if not isinstance(result.termination, str):
        fail("termination", "must be a string saying why it stopped")


def _validate_pose(fail, photo, pose, names: set[str]) -> None:
    where = f"poses['{photo}']"
    if photo not in names:
        fail("poses", f"name '{photo}', which is not one of the photos given")
    if not isinstance(pose, SfmPose):
        fail(where, f"is a {type(pose).__name__}; expected an SfmPose")
    R, t = np.asarray(pose.rotation), np.asarray(pose.translation)
    if R.shape != (3, 3) or t.shape != (3,):
        fail(where, f"rotation {R.shape} and translation {t.shape}; expected (3, 3) and (3,)")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        fail(where, "hold NaN or inf in the rotation or translation")
    off = float(np.abs(R @ R.T - np.eye(3)).max())
    if off > ORTHONORMAL or abs(np.linalg.det(R) - 1.0) > ORTHONORMAL:
        fail(f"{where}.rotation", f"is not a rotation (|R Rᵀ - I| = {off:.2g}, det {np.linalg.det(R):.6g}): "
             "return an orthonormal matrix of determinant +1")
    focal = pose.focal_px
    if not isinstance(focal, (int, float, np.floating, np.integer)) or not np.isfinite(focal) or focal <= 0:
        fail(f"{where}.focal_px", f"is {focal!r}; expected a finite number > 0")
    centre = np.asarray(pose.principal_point, dtype=object)
    if centre.shape != (2,) or not all(isinstance(v, (int, float, np.floating, np.integer)) and np.isfinite(v)
                                       for v in centre):
        fail(f"{where}.principal_point", f"is {pose.principal_point!r}; expected two finite numbers (x, y)")
