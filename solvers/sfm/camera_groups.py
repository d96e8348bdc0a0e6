"""Bundle adjustment of photos from several cameras: a focal length per camera.

Photos of several cameras (two phones, a zoom used at two settings) share a
focal length within each camera, not across them. Bundle adjustment fits one
focal length for all views or one per view; per view, each photo's focal
length trades against its depth, and poses come out several times worse than
from one camera (12 rendered photos, two cameras: 3.4 against 0.67 degrees
median relative-pose error). So, in two solves:

1. one focal length per view (:func:`.bundle.bundle_adjust` with
   ``shared_focal=False``); each camera's focal length is the median of its
   registered photos' (within 0.3 % of the truth on those 12 photos, where
   single photos were 6 % off);
2. a pinhole's image scaled about its principal point is the image of the
   same camera with its focal length scaled alike: each camera's keypoints
   are scaled by the first camera's focal length over its own, and one
   focal length fits them all, with every stage of the one-camera case (the
   grown pinhole start, the lens).

The result is in the photos' own pixels: each view's camera has its own
focal length back, and its residuals are scaled back (the fit's other pixel
figures, such as each camera model's RMS, by their root-mean-square factor). Where every photo has
a camera of its own (internet photos), there is nothing to share: step 1 is
the answer.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from mpe3d.solvers.sfm import bundle
from mpe3d.solvers.sfm.cameras import PINHOLES, Cameras, radial_cameras
from mpe3d.solvers.sfm.stages import Stage
from mpe3d.solvers.sfm.tracks import Tracks, principal_point_of, rms


def bundle_adjust_cameras(tracks: Tracks, view_cameras, camera: str = "auto", *, principal_point=None,
                          **options) -> bundle.BundleResult:
    """:func:`.bundle.bundle_adjust` for views of several cameras
    (``view_cameras``: each view's camera), a focal length per camera (the
    module's doc); ``options`` are bundle adjustment's, ``focal`` excepted."""
    groups = np.unique(np.asarray(view_cameras), return_inverse=True)[1].reshape(-1)
    c = principal_point_of(tracks, principal_point)
    start = time.perf_counter()
    per_view = bundle.bundle_adjust(tracks, camera, principal_point=c, shared_focal=False, **options)
    seconds = time.perf_counter() - start
    if per_view.cameras.model not in PINHOLES or groups.max() + 1 == len(groups):
        return per_view
    focal = _camera_focals(per_view, groups)
    if focal is None:
        return per_view
    scale = focal[groups[0]] / focal[groups]  # (K,) each view's keypoints' factor
    scaled = Tracks(tracks.view, tracks.point, c + scale[tracks.view, None] * (tracks.z - c), tracks.n_points,
                    tracks.n_views)
    shared = bundle.bundle_adjust(scaled, camera, principal_point=c, shared_focal=True, focal=float(focal[groups[0]]),
                                  **options)
    if shared.cameras.model not in PINHOLES:
        return per_view
    why = (f"{len(focal)} cameras: a focal length per view first, each camera's median "
           f"({', '.join(f'{f:.1f}' for f in focal)} px) scaling its keypoints to one focal length")
    residuals = shared.residuals / scale[tracks.view, None]
    # the other pixel figures are sums over views of the scaled keypoints: back by the
    # observations' root-mean-square factor (exact where every view's residuals are alike)
    back = float(np.sqrt(np.mean(scale[tracks.view[shared.counted]] ** -2.0))) if shared.counted.any() else 1.0
    by_camera = {model: value * back for model, value in shared.rms_by_camera.items()}
    by_camera[shared.camera] = rms(residuals[shared.counted])
    return dataclasses.replace(shared, cameras=_unscaled(shared.cameras, scale), residuals=residuals,
                               rms_by_camera=by_camera, rms_history=shared.rms_history * back,
                               affine_rms=shared.affine_rms * back, noise=shared.noise * back,
                               affine_misfit=shared.affine_misfit * back,
                               stages=(Stage("cameras", True, why, seconds), *shared.stages))


def _camera_focals(result: bundle.BundleResult, groups: np.ndarray) -> np.ndarray | None:
    """Each camera's focal length: its registered views' median; None when a
    camera has no registered view (no way to relate its scale to the others')."""
    registered = result.registered if result.registered is not None else np.ones(len(groups), dtype=bool)
    f = result.cameras.focal()
    out = []
    for g in range(int(groups.max()) + 1):
        mine = (groups == g) & registered & np.isfinite(f)
        if not mine.any():
            return None
        out.append(float(np.median(f[mine])))
    return np.array(out)


def _unscaled(cameras: Cameras, scale: np.ndarray) -> Cameras:
    """Shared-focal cameras of scaled keypoints as per-view cameras of the photos' own pixels."""
    cam = cameras.reanchored()
    focal = cam.focal() / scale
    if cam.model == "radial":
        return radial_cameras(cam.rotations, cam.params[:, 3:6], focal, cam.distortion(), cam.principal_point)
    params = np.concatenate([cam.params[:, :6], np.log(focal)[:, None]], axis=1)
    return Cameras(cam.model, cam.rotations, params, np.zeros(0), cam.principal_point)
