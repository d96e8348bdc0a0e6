"""COLMAP's incremental mapper as a method: the user's tracks through COLMAP.

The tracks (every observation: view, point, pixel) become a COLMAP database
in a scratch folder: one shared camera, an image per view, its observations
as keypoints, and for each pair of views the pairs of keypoints that one
track joins, as raw matches. COLMAP then does what it does to its own:
two-view geometric verification (F, E or H by RANSAC, COLMAP's thresholds),
and its incremental mapper (initial pair, registration by robust resection,
triangulation, bundle adjustment with Ceres, filtering of observations
beyond 4 px and of points under 1.5 degrees, re-triangulation, track
completion and merging). The largest model comes back in the user's terms:
each track's point (the 3D point most of its keypoints went to), each
view's camera, and every observation's residual under that camera, as a
:class:`~mpe3d.solvers.sfm.bundle.BundleResult` like bundle adjustment's.

COLMAP's camera for our models: ``radial`` and ``auto`` take its default,
SIMPLE_RADIAL (f, k); ``perspective`` its SIMPLE_PINHOLE. It has no affine
camera.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from mpe3d.errors import Unregistered
from mpe3d.options import COLMAP_CAMERAS
from mpe3d.solvers.sfm.bundle import BundleResult, place_unplaced
from mpe3d.solvers.sfm.cameras import radial_cameras
from mpe3d.solvers.sfm.colmap_link import require_pycolmap
from mpe3d.solvers.sfm.tracks import Tracks

# COLMAP's camera model for each of ours it takes (mpe3d.options.COLMAP_CAMERAS)
COLMAP_MODELS = {"auto": "SIMPLE_RADIAL", "radial": "SIMPLE_RADIAL", "perspective": "SIMPLE_PINHOLE"}
MIN_REGISTERED = 2  # views a model needs to be one


def track_matches(tracks: Tracks) -> tuple[np.ndarray, np.ndarray]:
    """The raw matches that the tracks imply: ``pairs`` (M, 2) views a < b and
    ``rows`` (M, 2) the two observations of each match (every pair of
    observations of one point, as a matcher would have linked them)."""
    order = np.lexsort((tracks.view, tracks.point))
    point = tracks.point[order]
    starts = np.flatnonzero(np.r_[True, point[1:] != point[:-1]])
    length = np.diff(np.r_[starts, len(point)])
    rank = np.arange(len(point)) - np.repeat(starts, length)
    length_of = np.repeat(length, length)
    a_rows, b_rows = [], []
    for gap in range(1, int(length.max(initial=1))):
        left = np.flatnonzero(rank + gap < length_of)
        a_rows.append(order[left])
        b_rows.append(order[left + gap])
    if not a_rows:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    rows = np.column_stack([np.concatenate(a_rows), np.concatenate(b_rows)])
    pairs = tracks.view[rows]
    swap = pairs[:, 0] > pairs[:, 1]
    rows[swap] = rows[swap][:, ::-1]
    pairs[swap] = pairs[swap][:, ::-1]
    keep = pairs[:, 0] != pairs[:, 1]  # one view twice: no match a matcher would make
    return pairs[keep], rows[keep]


def _write_database(pycolmap, path: Path, tracks: Tracks, keypoint: np.ndarray, camera, names):
    """One camera and rig, an image and frame per view, its keypoints, the raw matches."""
    with pycolmap.Database.open(str(path)) as db:
        camera.camera_id = db.write_camera(camera)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(camera.sensor_id)
        rig_id = db.write_rig(rig)
        image_ids = []
        for k, name in enumerate(names):
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=camera.camera_id))
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(pycolmap.data_t(camera.sensor_id, image_id))
            frame_id = db.write_frame(frame)
            image = db.read_image(image_id)
            image.frame_id = frame_id
            db.update_image(image)
            db.write_keypoints(image_id, tracks.z[tracks.view == k].astype(np.float32))
            image_ids.append(image_id)
        pairs, rows = track_matches(tracks)
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        pairs, rows = pairs[order], rows[order]
        cut = np.flatnonzero(np.any(np.diff(pairs, axis=0) != 0, axis=1)) + 1
        for chunk_pairs, chunk_rows in zip(np.split(pairs, cut), np.split(rows, cut)):
            if len(chunk_pairs):
                a, b = chunk_pairs[0]
                db.write_matches(image_ids[a], image_ids[b], keypoint[chunk_rows].astype(np.uint32))
    return image_ids


def colmap_map(tracks: Tracks, *, camera: str = "auto", principal_point=None, image_size=None,
               focal: float | None = None, seed: int = 0, threads: int = 1) -> BundleResult:
    """COLMAP's geometric verification and incremental mapper on ``tracks``.

    Parameters
    ----------
    tracks : Tracks
        The observations, in pixels.
    camera : {"auto", "radial", "perspective"}, default "auto"
        auto and radial: SIMPLE_RADIAL (COLMAP's default); perspective: SIMPLE_PINHOLE.
    principal_point : (2,) or None, default None
        Fixed, as COLMAP keeps it; None: the centre of the keypoints' bounding box.
    image_size : (width, height) or None, default None
        None: twice the principal point.
    focal : float or None, default None
        A trusted focal length in pixels (a plausible EXIF one): COLMAP's
        prior. None starts it at 1.2 times the larger image side, as COLMAP does.
    seed : int, default 0
        RANSAC's and the mapper's random seed.
    threads : int, default 1
        COLMAP's thread count for verification and mapping.

    ``seconds`` holds the time of verification and of mapping.
    """
    COLMAP_CAMERAS.check("camera", camera)
    pycolmap = require_pycolmap()
    lo, hi = tracks.z.min(axis=0), tracks.z.max(axis=0)
    c = np.asarray((lo + hi) / 2 if principal_point is None else principal_point, dtype=float)
    width, height = (np.ceil(np.maximum(2 * c, hi + 1)).astype(int) if image_size is None
                     else (int(image_size[0]), int(image_size[1])))
    prior = focal is not None
    f = float(focal) if prior else 1.2 * max(width, height)
    model = COLMAP_MODELS[camera]
    params = [f, c[0], c[1]] + ([0.0] if model == "SIMPLE_RADIAL" else [])
    cam = pycolmap.Camera(model=model, width=int(width), height=int(height), params=params)
    cam.has_prior_focal_length = prior
    keypoint = np.zeros(len(tracks.view), dtype=np.int64)  # each observation's index in its view
    for k in range(tracks.n_views):
        rows = np.flatnonzero(tracks.view == k)
        keypoint[rows] = np.arange(len(rows))
    names = [f"view{k:05d}" for k in range(tracks.n_views)]
    seconds = {}
    with tempfile.TemporaryDirectory(prefix="mpe3d-colmap-") as scratch:
        scratch = Path(scratch)
        database = scratch / "database.db"
        _write_database(pycolmap, database, tracks, keypoint, cam, names)
        pycolmap.set_random_seed(seed)
        start = time.perf_counter()
        verifier = pycolmap.GeometricVerifierOptions()
        verifier.num_threads = threads
        geometry = pycolmap.TwoViewGeometryOptions()
        geometry.ransac.random_seed = seed
        pycolmap.geometric_verification(str(database), verifier_options=verifier,
                                        two_view_geometry_options=geometry)
        seconds["verify_s"] = time.perf_counter() - start
        start = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = threads
        options.random_seed = seed
        options.extract_colors = False
        (scratch / "sparse").mkdir()
        models = pycolmap.incremental_mapping(str(database), str(scratch), str(scratch / "sparse"),
                                              options=options)
        seconds["map_s"] = time.perf_counter() - start
    best = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)
    if best is None or best.num_reg_images() < MIN_REGISTERED:
        raise Unregistered("COLMAP registered no two views: its geometric verification or its "
                       "initial pair found too few inlier matches among the tracks")
    return _result(best, tracks, keypoint, names, camera, c, len(models), seconds)


def _result(model, tracks: Tracks, keypoint, names, camera, c, n_models, seconds) -> BundleResult:
    """COLMAP's model in the tracks' terms (see :func:`colmap_map`)."""
    index = {name: k for k, name in enumerate(names)}
    K, N = tracks.n_views, tracks.n_points
    R, t = np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3))
    registered = np.zeros(K, dtype=bool)
    point3d = np.full(len(tracks.view), -1, dtype=np.int64)  # each observation's COLMAP point
    for image_id in model.reg_image_ids():
        image = model.images[image_id]
        k = index[image.name]
        pose = image.cam_from_world()
        R[k], t[k], registered[k] = pose.rotation.matrix(), pose.translation, True
        ids = np.array([p.point3D_id if p.has_point3D() else -1 for p in image.points2D], dtype=np.int64)
        rows = np.flatnonzero(tracks.view == k)
        point3d[rows] = ids[keypoint[rows]]
    X, placed = _track_points(model, tracks, point3d)
    params = np.asarray(next(iter(model.cameras.values())).params, dtype=float)
    k1 = params[3] if len(params) > 3 else 0.0
    cameras = radial_cameras(R, t, np.full(K, params[0]), np.array([k1, 0.0]), c, shared=True)
    chosen = np.full(N, -1, dtype=np.int64)
    chosen[placed] = X[1][placed]
    kept = (point3d >= 0) & (point3d == chosen[tracks.point]) & registered[tracks.view]
    dropped = ~kept & placed[tracks.point] & registered[tracks.view]
    points = place_unplaced(X[0], cameras, tracks, placed, kept | (~placed[tracks.point]
                                                                    & registered[tracks.view]))
    residuals = cameras.project(points, tracks.view, tracks.point) - tracks.z
    residuals[~registered[tracks.view]] = np.nan
    counted = kept & placed[tracks.point]
    rms = float(np.sqrt(np.mean(np.sum(residuals[counted] ** 2, axis=1)))) if counted.any() else np.nan
    return BundleResult(points=points, cameras=cameras, residuals=residuals, dropped=dropped,
                        counted=counted, converged=True, iterations=0,
                        termination=f"COLMAP's incremental mapper ({n_models} model(s), the "
                                    f"largest kept)",
                        affine_rms=float("nan"), camera=camera if camera != "auto" else "radial",
                        rms_by_camera={"radial" if camera == "auto" else camera: rms},
                        placed=placed, weak=np.zeros(N, dtype=bool), registered=registered,
                        seconds=seconds)


def _track_points(model, tracks: Tracks, point3d: np.ndarray):
    """((N, 3) points, (N,) their COLMAP ids), and (N,) placed: each track at the
    COLMAP point most of its keypoints went to."""
    N = tracks.n_points
    X, chosen = np.zeros((N, 3)), np.full(N, -1, dtype=np.int64)
    has = point3d >= 0
    if not has.any():
        return (X, chosen), np.zeros(N, dtype=bool)
    pairs, votes = np.unique(np.column_stack([tracks.point[has], point3d[has]]), axis=0,
                             return_counts=True)
    order = np.lexsort((-votes, pairs[:, 0]))  # per track, the most votes first
    pairs = pairs[order]
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    for track, pid in pairs[first]:
        chosen[track] = pid
        X[track] = model.points3D[int(pid)].xyz
    return (X, chosen), chosen >= 0
