"""COLMAP's mappers as methods: the user's tracks through COLMAP.

The tracks (every observation: view, point, pixel) become a COLMAP database
in a scratch folder: a camera (one for all views, or one per camera of
photos from several), an image per view, its observations as keypoints, and
for each pair of views the pairs of keypoints that one track joins, as raw
matches. COLMAP then does what it does to its own: two-view geometric
verification (F, E or H by RANSAC, COLMAP's thresholds), and one of its two
mappers: the incremental one (initial pair, registration by robust
resection, triangulation, bundle adjustment with Ceres, filtering of
observations beyond 4 px and of points under 1.5 degrees, re-triangulation,
track completion and merging), or the global one (GLOMAP's: every view's
rotation at once by rotation averaging of the verified pairs' relative
poses, then the cameras' positions and the points together by global
positioning, then bundle adjustment and re-triangulation).
The largest model comes back in the user's terms: each track's point (the 3D
point most of its keypoints went to, :func:`majority_points`), each view's
camera, and every observation's residual under that camera, as a
:class:`~mpe3d.solvers.sfm.bundle.BundleResult` like bundle adjustment's.
Every pycolmap call is :mod:`.colmap`'s.

COLMAP's camera for our models: ``radial`` and ``auto`` take its default,
SIMPLE_RADIAL (f, k); ``perspective`` its SIMPLE_PINHOLE. It has no affine
camera.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mpe3d.errors import Unregistered
from mpe3d.options import COLMAP_CAMERAS, COLMAP_MAPPERS, OUTLIER_THRESHOLD
from mpe3d.solvers.sfm import colmap
from mpe3d.solvers.sfm.bundle import BundleResult, place_unplaced
from mpe3d.solvers.sfm.cameras import radial_cameras
from mpe3d.solvers.sfm.tracks import Tracks, principal_point_of

# COLMAP's camera model for each of ours it takes (mpe3d.options.COLMAP_CAMERAS)
COLMAP_MODELS = {"auto": "SIMPLE_RADIAL", "radial": "SIMPLE_RADIAL", "perspective": "SIMPLE_PINHOLE"}
# What COLMAP's mapper cannot be asked: it poses its own cameras from its own
# start, with its own camera models, loss and filter. Each option: the values
# it takes, and what COLMAP has of its own instead.
COLMAP_TAKES = {"camera": (COLMAP_CAMERAS.names, "camera models (no affine one)"),
                "loss": (("l2",), "loss (a trivial one)"),
                "start": (("own",), "start (its initial pair)"),
                "outlier_threshold": ((OUTLIER_THRESHOLD,), "filter (4 px)")}


MAPPING = {"incremental": colmap.incremental_mapping, "global": colmap.global_mapping}


def refused(option: str, value) -> str | None:
    """Why COLMAP's mappers cannot be asked ``option=value``; None when it can."""
    allowed, own = COLMAP_TAKES[option]
    if value in allowed:
        return None
    if option == "camera":
        return f"COLMAP has no affine camera; its mapper takes camera {' or '.join(allowed)}"
    return f"bundle adjustment's; COLMAP's mapper has its own {own}, so {option} stays {allowed[0]}"


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


def _database_parts(tracks: Tracks, keypoint: np.ndarray):
    """Each view's keypoints, and the raw matches of each pair of views."""
    keypoints = [tracks.z[tracks.view == k] for k in range(tracks.n_views)]
    pairs, rows = track_matches(tracks)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    pairs, rows = pairs[order], rows[order]
    cut = np.flatnonzero(np.any(np.diff(pairs, axis=0) != 0, axis=1)) + 1
    chunks = [(p[0], keypoint[r]) for p, r in zip(np.split(pairs, cut), np.split(rows, cut)) if len(p)]
    return keypoints, np.array([c[0] for c in chunks], dtype=np.int64).reshape(-1, 2), [c[1] for c in chunks]


def _cameras(tracks: Tracks, camera: str, c, image_size, focal, view_cameras):
    """COLMAP's cameras for the views and each view's camera: one shared, or
    one per group of ``view_cameras`` (then ``image_size`` is per view)."""
    groups = np.zeros(tracks.n_views, dtype=np.int64) if view_cameras is None \
        else np.unique(np.asarray(view_cameras), return_inverse=True)[1].astype(np.int64)
    sizes = np.atleast_2d(np.asarray(image_size, dtype=float)) if image_size is not None else None
    out = []
    for g in range(int(groups.max()) + 1):
        if sizes is None:
            width, height = colmap.keypoint_box(tracks.z, c)
        else:
            width, height = sizes[np.flatnonzero(groups == g)[0] if len(sizes) > 1 else 0].astype(int)
        prior = focal is not None and view_cameras is None
        f = float(focal) if prior else 1.2 * max(width, height)
        out.append(colmap.simple_camera(COLMAP_MODELS[camera], width, height, f, c, prior, camera_id=g + 1))
    return out, groups


def colmap_map(tracks: Tracks, *, camera: str = "auto", principal_point=None, image_size=None,
               focal: float | None = None, seed: int = 0, threads: int = 1,
               view_cameras=None, scratch: Path | None = None, mapper: str = "incremental") -> BundleResult:
    """COLMAP's geometric verification and ``mapper`` on ``tracks``.

    Parameters
    ----------
    tracks : Tracks
        The observations, in pixels.
    camera : {"auto", "radial", "perspective"}, default "auto"
        auto and radial: SIMPLE_RADIAL (COLMAP's default); perspective: SIMPLE_PINHOLE.
    principal_point : (2,) or None, default None
        Fixed, as COLMAP keeps it; None: the centre of the keypoints' bounding box.
    image_size : (width, height), (K, 2) with ``view_cameras``, or None, default None
        None: what holds the keypoints round the principal point (:func:`.colmap.keypoint_box`).
    focal : float or None, default None
        A trusted focal length in pixels (a plausible EXIF one): COLMAP's
        prior. None starts it at 1.2 times the larger image side, as COLMAP does.
    seed : int, default 0
        RANSAC's and the mapper's random seed.
    threads : int, default 1
        COLMAP's thread count for verification; its mappers run on one, so
        that a seed repeats a run (:mod:`.colmap`).
    view_cameras : (K,) ints or None, default None
        Each view's camera, for photos of several cameras (each its own focal
        length, started as COLMAP does); None: one camera for all.
    scratch : folder or None, default None
        Where COLMAP's database goes (its space checked first); None: the
        system's temporary folder.
    mapper : {"incremental", "global"}, default "incremental"
        COLMAP's incremental mapper, or its global one (GLOMAP's).

    ``seconds`` holds the time of verification (``verify_s``) and of mapping (``map_s``).
    """
    COLMAP_CAMERAS.check("camera", camera)
    COLMAP_MAPPERS.check("mapper", mapper)
    c = principal_point_of(tracks, principal_point)
    cameras, groups = _cameras(tracks, camera, c, image_size, focal, view_cameras)
    keypoint = np.zeros(len(tracks.view), dtype=np.int64)  # each observation's index in its view
    for k in range(tracks.n_views):
        rows = np.flatnonzero(tracks.view == k)
        keypoint[rows] = np.arange(len(rows))
    names = [f"view{k:05d}" for k in range(tracks.n_views)]
    seconds = {}
    parts = _database_parts(tracks, keypoint)
    # keypoints, and each match twice (raw, then its verified inliers)
    need = len(tracks.view) * colmap.FEATURE_BYTES + sum(map(len, parts[2])) * 2 * colmap.MATCH_BYTES
    with colmap.scratch(scratch, need) as folder:
        database = folder / "database.db"
        colmap.write_database(database, names, cameras, groups, *parts)
        start = time.perf_counter()
        colmap.verify_matches(database, threads=threads, seed=seed)
        seconds["verify_s"] = time.perf_counter() - start
        model = MAPPING[mapper](database, folder, folder / "sparse", seed=seed)
    if model is None or len(model.images) < colmap.MIN_REGISTERED:
        start = "initial pair" if mapper == "incremental" else "rotation averaging"
        raise Unregistered(f"COLMAP's {mapper} mapper registered no two views: its geometric verification or "
                           f"its {start} found too few inlier matches among the tracks")
    seconds.update(model.seconds)
    return _result(model, tracks, keypoint, names, camera, c, cameras, groups, seconds, mapper)


def _result(model: colmap.Model, tracks: Tracks, keypoint, names, camera, c, started, groups,
            seconds, mapper) -> BundleResult:
    """COLMAP's model in the tracks' terms (see :func:`colmap_map`); a view it
    left out keeps its camera's start (COLMAP drops the cameras no registered
    image uses)."""
    K, N = tracks.n_views, tracks.n_points
    R, t = np.tile(np.eye(3), (K, 1, 1)), np.zeros((K, 3))
    registered = np.zeros(K, dtype=bool)
    point3d = np.full(len(tracks.view), -1, dtype=np.int64)  # each observation's COLMAP point
    focal, k1 = np.zeros(K), np.zeros(K)
    for k, name in enumerate(names):
        image = model.images.get(name)
        params = (started[groups[k]] if image is None else model.cameras[image.camera_id]).params
        focal[k], k1[k] = params[0], params[3] if len(params) > 3 else 0.0
        if image is None:
            continue
        R[k], t[k], registered[k] = image.rotation, image.translation, True
        rows = np.flatnonzero(tracks.view == k)
        point3d[rows] = image.point3d[keypoint[rows]]
    chosen = majority_points(tracks.point, point3d, N)
    placed = chosen >= 0
    X = np.zeros((N, 3))
    X[placed] = model.point_of(chosen[placed])
    shared = groups.max() == 0
    one = int(np.flatnonzero(registered)[0])  # one camera for all: as a registered view has it, refined
    cameras = radial_cameras(R, t, focal[one:one + 1] if shared else focal,
                             np.array([k1[one], 0.0]) if shared else np.column_stack([k1, np.zeros(K)]),
                             c, shared=bool(shared))
    kept = (point3d >= 0) & (point3d == chosen[tracks.point]) & registered[tracks.view]
    dropped = ~kept & placed[tracks.point] & registered[tracks.view]
    points = place_unplaced(X, cameras, tracks, placed, kept | (~placed[tracks.point]
                                                                & registered[tracks.view]))
    residuals = cameras.project(points, tracks.view, tracks.point) - tracks.z
    residuals[~registered[tracks.view]] = np.nan
    counted = kept & placed[tracks.point]
    rms = float(np.sqrt(np.mean(np.sum(residuals[counted] ** 2, axis=1)))) if counted.any() else np.nan
    return BundleResult(points=points, cameras=cameras, residuals=residuals, dropped=dropped,
                        counted=counted, converged=True, iterations=0,
                        termination=f"COLMAP's {mapper} mapper ({model.models} model(s), the "
                                    f"largest kept)",
                        affine_rms=float("nan"), camera=camera if camera != "auto" else "radial",
                        rms_by_camera={"radial" if camera == "auto" else camera: rms},
                        placed=placed, weak=np.zeros(N, dtype=bool), registered=registered,
                        seconds=seconds)


def majority_points(track: np.ndarray, point3d: np.ndarray, n_tracks: int) -> np.ndarray:
    """(n_tracks,) each track's COLMAP point: the point3D id most of its
    keypoints went to (``point3d`` per observation, -1 for none; ties to the
    lower id), -1 where none went anywhere."""
    chosen = np.full(n_tracks, -1, dtype=np.int64)
    has = point3d >= 0
    if not has.any():
        return chosen
    pairs, votes = np.unique(np.column_stack([np.asarray(track)[has], point3d[has]]), axis=0,
                             return_counts=True)
    order = np.lexsort((-votes, pairs[:, 0]))  # per track, the most votes first
    pairs = pairs[order]
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    chosen[pairs[first, 0]] = pairs[first, 1]
    return chosen
