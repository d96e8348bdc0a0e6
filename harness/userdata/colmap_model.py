"""COLMAP sparse models in and out, through pycolmap.

:func:`read_model` reads a model folder (``cameras``, ``images``,
``points3D``, binary or text) as keypoint views for
:func:`mpe3d.harness.userdata.reconstruct.reconstruct`; :func:`write_model`
writes a reconstruction back as a model that COLMAP's GUI opens.
Running COLMAP on photos is :mod:`mpe3d.harness.experiment.colmap_sfm`'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.solvers.sfm import colmap

MODEL_FILES = ("cameras", "images", "points3D")
# An affine camera written as a pinhole this many cloud diameters away: its
# projection differs from the affine one by about 1 / FAR of the image extent.
FAR = 1000.0


def model_files(folder: Path) -> str | None:
    """"bin" or "txt" when ``folder`` holds a COLMAP sparse model, else None."""
    for ext in ("bin", "txt"):
        if all((folder / f"{name}.{ext}").is_file() for name in MODEL_FILES):
            return ext
    return None


def _check_model_folder(folder: Path) -> None:
    present = [p.name for p in folder.iterdir() if p.stem in MODEL_FILES]
    if not present:
        return
    for ext in ("bin", "txt"):
        missing = [f"{n}.{ext}" for n in MODEL_FILES if not (folder / f"{n}.{ext}").is_file()]
        if len(missing) < len(MODEL_FILES) and missing:
            raise MpeError(f"{folder}: an incomplete COLMAP model: {', '.join(missing)} missing")


def looks_like_model(folder: Path) -> bool:
    """True for a folder with COLMAP model files (complete or not: then an error says what lacks)."""
    if not folder.is_dir():
        return False
    _check_model_folder(folder)
    return model_files(folder) is not None


# The least bytes one record of each binary file can take: a count beyond what
# the file can hold is a damaged file, which COLMAP would try to read for minutes.
MIN_RECORD_BYTES = {"cameras": 24, "images": 73, "points3D": 51}


def _check_binary_counts(folder: Path) -> None:
    for name, least in MIN_RECORD_BYTES.items():
        path = folder / f"{name}.bin"
        size = path.stat().st_size
        count = int.from_bytes(path.read_bytes()[:8], "little") if size >= 8 else -1
        if count < 0 or count * least > size - 8:
            raise MpeError(f"{path}: damaged ({size} bytes cannot hold the "
                           f"{max(count, 0):,} records its header declares)")


def read_model(folder: str | Path) -> list[dict]:
    """A COLMAP sparse model as keypoint views: one per registered image, its
    point3D ids as ids and their keypoints in pixels.

    The keypoints are taken through each image's own camera model (distortion
    included) to normalised coordinates and back through one shared pinhole
    (the mean focal length, the first camera's principal point), so that
    every view has the camera that ``camera="perspective"`` fits; each view
    dict carries that ``principal_point``.
    """
    folder = Path(folder)
    if model_files(folder) is None:
        _check_model_folder(folder)
        raise MpeError(f"{folder}: no COLMAP model (cameras, images and points3D as .bin or .txt)")
    if model_files(folder) == "bin":
        _check_binary_counts(folder)
    model = colmap.read_model(folder)
    if not model.cameras:
        raise MpeError(f"{folder}: the COLMAP model has no cameras")
    cameras = [model.cameras[i].check(str(folder)) for i in sorted(model.cameras)]
    focal = float(np.mean([c.focal for c in cameras]))
    centre = cameras[0].principal_point
    views = []
    for name, image in model.images.items():
        has = image.point3d >= 0
        if not has.any():
            continue
        xy = model.cameras[image.camera_id].to_pinhole(image.xy[has], focal, centre)
        views.append({"name": name, "ids": image.point3d[has], "xy": xy, "principal_point": centre})
    if len(views) < 2:
        raise MpeError(f"{folder}: the COLMAP model has {len(views)} registered image(s) with "
                       "points; at least 2 are needed")
    return views


def _pinhole(camera, principal_point, diameter: float):
    """(fx, fy, c, R, T) of a :class:`~.results.ViewCamera`: the pinhole
    itself (a given 3x4 matrix read as P = K [R | T]), or an affine camera as
    a pinhole FAR diameters away that projects the same to 1 / FAR."""
    if camera.rotation is None:
        return _decomposed(camera.P)
    R = camera.rotation
    if camera.focal_px is not None:
        K = camera.P[:, :3] @ R.T
        return camera.focal_px, camera.focal_px, K[:2, 2] / K[2, 2], R, camera.translation
    s = camera.scale
    depth = FAR * diameter
    t = (camera.translation_px - principal_point) / s
    return s * depth, s * depth, principal_point, R, np.array([t[0], t[1], depth])


def _decomposed(P: np.ndarray):
    """(fx, fy, c, R, T) of a 3x4 matrix P = K [R | T]: K R by RQ, signs made positive."""
    from scipy.linalg import rq

    K, R = rq(P[:, :3])
    signs = np.sign(np.diag(K))
    K, R = K * signs, signs[:, None] * R
    T = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:
        R, T = -R, -T
    K = K / K[2, 2]
    return float(K[0, 0]), float(K[1, 1]), K[:2, 2], R, T


def write_model(folder: str | Path, points: np.ndarray, ids: np.ndarray, views: list[dict],
                cameras: list | None, principal_point, image_size=None,
                dropped=()) -> list[str]:
    """``points`` as a COLMAP binary model in ``folder`` (created): a PINHOLE
    camera and a posed image per view with its keypoints, and each point with
    its track. Returns notes for what the model cannot say exactly.

    ``views`` are the keypoint views solved (names, ids, xy; an ``image_size``
    of its own where photos differ); ``cameras`` their
    :class:`~.results.ViewCamera` in the same order (None: points only, no images);
    ``dropped`` the (view name, id) pairs left out as wrong matches.
    """
    folder = Path(folder)
    notes = []
    numeric = ids.dtype.kind in "iu" and len(ids) and ids.min() >= 0 and ids.max() < 2 ** 63 - 1
    point_id = (ids.astype(np.int64) + (1 if numeric and ids.min() == 0 else 0)) if numeric \
        else np.arange(1, len(ids) + 1)
    if not numeric or ids.min() == 0:
        notes.append("COLMAP point3D ids are positive integers: point i of the cloud has id "
                     + ("its id + 1" if numeric else "i + 1 (the order of the written cloud)"))
    row = {key: i for i, key in enumerate(ids.tolist())}
    tracks: dict[int, list] = {}
    images = []
    if cameras is not None:
        diameter = float(np.linalg.norm(np.ptp(points, axis=0))) or 1.0
        c = np.asarray(principal_point, dtype=float)
        width, height = image_size or np.ceil(2 * c).astype(int)
        if any(cam.focal_px is None and cam.rotation is not None for cam in cameras):
            notes.append(f"COLMAP has no affine camera: each view is written as a pinhole "
                         f"{FAR:g} cloud diameters away, which projects like it to 1/{FAR:g}")
        skip = {(str(v), str(i)) for v, i in dropped}
        for k, (view, camera) in enumerate(zip(views, cameras)):
            if not camera.registered:  # COLMAP's mapper left it out: no pose to write
                continue
            fx, fy, centre, R, T = _pinhole(camera, c, diameter)
            name = str(view.get("name", k))
            keep = [j for j, i in enumerate(view["ids"]) if (name, str(i)) not in skip]
            size = view.get("image_size", (width, height))
            pinhole = colmap.Camera("PINHOLE", int(size[0]), int(size[1]), (fx, fy, centre[0], centre[1]))
            images.append(colmap.PosedImage(name if "." in name else f"{name}.png", pinhole, R, T,
                                            np.asarray(view["xy"], dtype=float)[keep]))
            for j, i in enumerate(np.asarray(view["ids"])[keep].tolist()):
                if i in row:  # a point left out (unplaced) keeps its keypoint, not a track
                    tracks.setdefault(row[i], []).append((len(images) - 1, j))
    colmap.write_model(folder, images, point_id, points, tracks)
    return notes


def check_model_out(folder: Path) -> Path:
    """``folder`` if a COLMAP model can be written there: new, empty, or an
    older model (replaced); checked before any work."""
    import tempfile

    if folder.exists() and not folder.is_dir():
        raise MpeError(f"--out {folder}: a file, not a folder (a COLMAP model is a folder; "
                       "give .ply, .csv or .npy for a cloud file)")
    if folder.is_dir() and any(folder.iterdir()) and model_files(folder) is None:
        raise MpeError(f"--out {folder}: the folder holds other files; a COLMAP model goes into "
                       "a new or empty folder (or replaces a model)")
    parent = folder if folder.is_dir() else folder.parent
    if not parent.is_dir():
        raise MpeError(f"--out {folder}: folder {parent} does not exist")
    try:
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".mpe3d-", suffix=".probe"):
            pass
    except OSError as exc:
        raise MpeError(f"--out {folder}: cannot write in {parent} ({exc.strerror or exc})") from None
    return folder


def write_model_folder(folder: Path, problem, result) -> list[str]:
    """The solved cloud of ``mpe3d reconstruct`` as a COLMAP model in ``folder``
    (its PLY is written beside by the caller); returns notes for the report."""
    obs, ids = problem.observations, problem.ids
    views = [{"name": name, "ids": ids[view.ids], "xy": view.coordinates}
             for name, view in zip(problem.view_names, obs.views)]
    if problem.view_offsets is not None:  # photos of several cameras: each in its own pixels
        views = [{**view, "xy": view["xy"] + offset, "image_size": tuple(size)}
                 for view, offset, size in zip(views, problem.view_offsets, problem.image_sizes)]
    if result.objective != "reprojection" or any(v["xy"] is None for v in views):
        cameras, centre = None, np.zeros(2)
        notes = ["the COLMAP model holds the points only: distance matrices give no keypoints "
                 "and no pinhole cameras"]
    else:
        cameras = list(result.cameras)
        one = next(c for c in cameras if c.registered)
        first = _pinhole(one, np.zeros(2), 1.0)[2] if one.focal_px is not None \
            or one.rotation is None else None
        centre = np.asarray(first if first is not None else problem.principal_point or (0.0, 0.0),
                            dtype=float)
        notes = []
    placed = ~np.isin(ids, result.unplaced.astype(ids.dtype))
    return notes + write_model(folder, result.points[placed], ids[placed], views, cameras, centre,
                               None, result.dropped)
