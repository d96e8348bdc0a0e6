"""What :func:`mpe3d.harness.userdata.reconstruct.reconstruct` returns: the
cloud, each view's camera, and the report written from them (every number a
user is told about a solve, its stages and its code)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpe3d.harness.tracking.identity import code_identity
from mpe3d.solvers.sfm.support import FAR_FACTOR, MIN_RAY_ANGLE


@dataclass(frozen=True)
class ViewCamera:
    """One view's fitted camera. A pinhole: ``P = K [R | translation]`` with
    ``focal_px``; an affine camera (orthographic or scaled): ``P = scale R[:2]``
    plus ``translation_px`` in the image; a given 3x4 matrix: ``P`` only."""

    view: str
    P: np.ndarray  # (3, 4) pinhole, (2, 3) affine
    rotation: np.ndarray | None = None  # (3, 3)
    focal_px: float | None = None
    translation: np.ndarray | None = None  # (3,) pinhole
    scale: float | None = None
    translation_px: np.ndarray | None = None  # (2,) affine
    k1: float | None = None  # radial distortion (the radial camera)
    k2: float | None = None
    registered: bool = True  # False: the solve left the view out, no pose agreeing with it (P is NaN)

    @classmethod
    def from_numbers(cls, view: str, numbers: dict) -> "ViewCamera":
        """From :meth:`mpe3d.solvers.sfm.cameras.Cameras.matrices`' plain numbers."""
        arrays = {k: np.asarray(v, dtype=float) for k, v in numbers.items()
                  if k in ("P", "rotation", "translation", "translation_px")}
        plain = {k: float(v) for k, v in numbers.items() if k in ("focal_px", "scale", "k1", "k2")}
        return cls(view, **arrays, **plain)

    def numbers(self) -> dict[str, Any]:
        """The camera as the report writes it (JSON-ready, fields in the report's order)."""
        if not self.registered:
            return {"registered": False}
        if self.rotation is None:
            return {"P": self.P.tolist()}
        if self.focal_px is not None:
            distortion = {} if self.k1 is None else {"k1": self.k1, "k2": self.k2}
            return {"focal_px": self.focal_px, **distortion, "rotation": self.rotation.tolist(),
                    "translation": self.translation.tolist(), "P": self.P.tolist()}
        return {"scale": self.scale, "rotation": self.rotation.tolist(),
                "translation_px": self.translation_px.tolist(), "P": self.P.tolist()}


@dataclass
class Result:
    """A reconstruction of user data: the cloud, its ids, and what to trust about it.

    The typed fields are the result; :attr:`report` is the JSON report
    written from them (and from ``facts``, the numbers that only it shows),
    never read back as data.
    """

    points: np.ndarray  # (N, 3), in the frame of the given cameras when fixed
    ids: np.ndarray  # (N,) the input's point ids, in the order of ``points``
    projections: np.ndarray  # (K, 2, 3) orthonormal rows, given or estimated
    objective: str = "stress"
    cameras: tuple[ViewCamera, ...] = ()  # reprojection: each view's fitted camera
    dropped: tuple[tuple[str, Any], ...] = ()  # (view name, point id): taken for wrong matches
    unplaced: np.ndarray = field(default_factory=lambda: np.zeros(0))  # ids with no depth fixed
    warnings: list[str] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)
    # reprojection: per observation, in the input's order (view by view, each
    # view's rows as given), the residual in pixels, and whether rms counts it
    residuals: np.ndarray | None = None  # (M, 2)
    counted: np.ndarray | None = None  # (M,) bool

    @property
    def report(self) -> dict[str, Any]:
        """The JSON report (:func:`mpe3d.harness.userdata.formats.write_result` writes it)."""
        return {**self.facts, "warnings": self.warnings}


def stress_result(problem, rec, runtime: float, warnings: list[str]) -> Result:
    from mpe3d.solvers.stress import Stress

    obs, ids = problem.observations, problem.ids
    stress = Stress(obs)
    projections = np.asarray(rec.projections)
    rms = stress.view_rms(rec.points, projections)
    seen = obs.visibility().sum(axis=0)
    unplaced = ids[seen < 2]
    facts = {
        "points": int(obs.n_points), "views": int(obs.n_views), "objective": "stress",
        "setting": "fixed" if obs.fixed else "variable", "solver": problem.solver,
        "loss": problem.loss, "stress": float(stress.value(rec.points, projections)),
        "stress_pairs": "sparse (k-NN and random pairs per view)" if stress.sparse else "all",
        "rms_residual_per_view": [float(r) for r in rms],
        "unplaced": {"count": int(len(unplaced)), "ids": unplaced.tolist()},
        "projections": projections.tolist(),
        "iterations": int(rec.iterations), "termination": rec.termination,
        "rejected": int(rec.info.get("rejected", 0)),  # refine's rows taken for outliers
        "runtime_s": runtime, "code": code_identity(),
    }
    return Result(points=rec.points, ids=ids, projections=projections, objective="stress",
                  unplaced=unplaced, warnings=warnings, facts=facts)


def _own_principal_point(camera: ViewCamera, offset) -> ViewCamera:
    """A pinhole solved round the shared principal point, in its photo's own
    pixels: its image moved by ``offset`` (the photo's principal point less
    the shared one)."""
    if not camera.registered or camera.focal_px is None:
        return camera
    shift = np.eye(3)
    shift[:2, 2] = offset
    return dataclasses.replace(camera, P=shift @ camera.P)


def reprojection_result(problem, tracks, fit, runtime: float,
                         warnings: list[str]) -> Result:
    """Reprojection RMS per view in pixels, the cameras (and as ``projections``
    their rotations' first rows, or the given 3x4 matrices), the dropped
    observations."""
    obs, ids, names = problem.observations, problem.ids, problem.view_names
    length2 = np.sum(fit.residuals ** 2, axis=1)
    kept = fit.counted  # the kept observations of the placed points
    per_view = [float(np.sqrt(np.mean(length2[(tracks.view == k) & kept])))
                if np.any((tracks.view == k) & kept) else None for k in range(obs.n_views)]
    dropped = tuple((names[k], _plain(ids[i]))
                    for k, i in zip(tracks.view[fit.dropped], tracks.point[fit.dropped]))
    unplaced = ids[~fit.placed]
    weak = int(fit.weak.sum())
    registered = fit.registered
    cameras = tuple(ViewCamera.from_numbers(name, numbers) if seen else
                    ViewCamera(name, np.full((3, 4), np.nan), registered=False)
                    for name, numbers, seen in zip(names, fit.cameras.matrices(), registered))
    if problem.view_offsets is not None:
        cameras = tuple(_own_principal_point(c, offset) for c, offset in zip(cameras, problem.view_offsets))
    projections = np.asarray(fit.cameras.current_rotations()[:, :2]
                             if fit.cameras.model != "matrix" else problem.cameras)
    unregistered = [name for name, seen in zip(names, registered) if not seen]
    if unregistered:
        warnings = warnings + [f"{int(registered.sum())} of {len(names)} views registered (no pose "
                               f"agrees with enough of their tracks); left out: {', '.join(unregistered[:10])}"
                               + (" ..." if len(unregistered) > 10 else "")]
    facts = {
        "points": int(obs.n_points), "views": int(obs.n_views), "objective": "reprojection",
        "setting": "fixed" if problem.cameras is not None else "variable",
        "solver": problem.solver, "camera": fit.camera, "loss": problem.loss,
        "reprojection_rms_px": fit.rms(), "reprojection_rms_px_all": fit.rms(np.ones_like(kept)),
        "rms_px_per_view": per_view,
        "rms_px_by_camera": {model: float(v) for model, v in fit.rms_by_camera.items()},
        "affine_rms_px": None if not np.isfinite(fit.affine_rms) else float(fit.affine_rms),
        "keypoint_noise_px": _finite(fit.noise), "affine_misfit_px": _finite(fit.affine_misfit),
        "cameras": [{"view": c.view, **c.numbers()} for c in cameras],
        "unregistered": unregistered,
        "projections": [p.tolist() if seen else None for p, seen in zip(projections, registered)],
        "dropped": {"count": len(dropped), "threshold_sigmas": problem.outlier_threshold,
                    "observations": [{"view": v, "point": i} for v, i in dropped]},
        "unplaced": {"count": int(len(unplaced)), "ids": unplaced.tolist(),
                     "weak_geometry": weak,  # of them: placed, but their depth is not fixed
                     "rule": f"seen in fewer than 2 views, or rays meeting under "
                             f"{MIN_RAY_ANGLE:g} degrees, or farther than {FAR_FACTOR:g} times "
                             "the cloud's median radius"},
        "converged": bool(fit.converged), "iterations": int(fit.iterations),
        "termination": fit.termination, "runtime_s": runtime, "code": code_identity(),
        "stages": [stage.numbers() for stage in fit.stages],
        **({"colmap_seconds": fit.seconds} if fit.seconds else {}),
    }
    return Result(points=fit.points, ids=ids, projections=projections, objective="reprojection",
                  cameras=cameras, dropped=dropped, unplaced=unplaced, warnings=warnings,
                  facts=facts, residuals=fit.residuals, counted=fit.counted)


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _plain(value):
    return value.item() if hasattr(value, "item") else value
