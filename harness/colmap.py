"""COLMAP through pycolmap: structure from motion on photos, and COLMAP models in and out.

Three jobs, each kept to pycolmap's own calls:

* :func:`run_sfm`: SIFT extraction, matching (exhaustive for few photos,
  sequential along the camera path for many) and incremental mapping, on
  one thread with a fixed seed so that a run repeats;
* :func:`database_tracks`: COLMAP's feature tracks, the connected
  components of its geometrically verified matches, before any
  triangulation (what the paper fed to 3DMPE);
* :func:`read_model` / :func:`write_model`: a sparse model folder
  (``cameras``, ``images``, ``points3D``, binary or text) as keypoint views
  for :func:`mpe3d.harness.reconstruct.reconstruct`, and a reconstruction
  written back as a model that COLMAP's GUI opens.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MpeError

MODEL_FILES = ("cameras", "images", "points3D")
EXHAUSTIVE_UP_TO = 50  # photos; beyond, matching pairs each photo with its path neighbours
SEQUENTIAL_OVERLAP = 10  # neighbours on each side of a photo along the path
# An affine camera written as a pinhole this many cloud diameters away: its
# projection differs from the affine one by about 1 / FAR of the image extent.
FAR = 1000.0


def require_pycolmap():
    """pycolmap, or one line saying how to get it."""
    try:
        import pycolmap
    except ImportError:
        raise MpeError("COLMAP support needs pycolmap: pip install pycolmap") from None
    logging = getattr(pycolmap, "logging", None)
    if logging is not None and hasattr(logging, "minloglevel"):
        logging.minloglevel = 2  # errors only: glog's progress lines are not ours to print
    return pycolmap


def colmap_version() -> str:
    pycolmap = require_pycolmap()
    return f"pycolmap {pycolmap.__version__} ({pycolmap.COLMAP_version})"


# -- structure from motion ------------------------------------------------------

@dataclass
class SfmResult:
    """What COLMAP made of a set of photos (the largest model, if any)."""

    database: Path
    names: list[str]  # the photos, in path order
    points: np.ndarray  # (P, 3) the largest model's points, COLMAP's frame
    point_ids: np.ndarray  # (P,) their point3D ids
    registered: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (R, t), world -> camera
    models: int  # how many separate models the mapper made
    focal: float | None  # the refined focal length of the largest model
    reprojection_px: float | None  # its mean reprojection error
    image_points: dict[str, dict[int, int]] = field(default_factory=dict)  # name -> {keypoint: point3D}
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def centres(self) -> dict[str, np.ndarray]:
        return {name: -R.T @ t for name, (R, t) in self.registered.items()}


def matching_for(count: int, matching: str = "auto") -> str:
    if matching != "auto":
        return matching
    return "exhaustive" if count <= EXHAUSTIVE_UP_TO else "sequential"


def run_sfm(image_dir: Path, names: list[str], workdir: Path, *, focal: float,
            principal_point, matching: str = "auto", seed: int = 0,
            max_features: int = 8192) -> SfmResult:
    """COLMAP on ``names`` in ``image_dir``: one shared SIMPLE_PINHOLE camera
    started at ``focal`` (refined by the mapper, as for photos whose EXIF
    gives the focal length), SIFT, matching, incremental mapping."""
    pycolmap = require_pycolmap()
    pycolmap.set_random_seed(seed)
    database = workdir / "database.db"
    database.unlink(missing_ok=True)
    seconds = {}
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    reader.camera_params = f"{focal},{principal_point[0]},{principal_point[1]}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1
    extraction.sift.max_num_features = max_features
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["extract_s"] = time.perf_counter() - start
    start = time.perf_counter()
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    if matching_for(len(names), matching) == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=options, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.loop_detection = False  # needs a vocabulary tree file; the path is closed anyway
        pycolmap.match_sequential(database, matching_options=options, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    seconds["match_s"] = time.perf_counter() - start
    start = time.perf_counter()
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = 1
    mapping.random_seed = seed
    sparse = workdir / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    models = pycolmap.incremental_mapping(database, image_dir, sparse, options=mapping)
    seconds["map_s"] = time.perf_counter() - start
    return _largest(models, database, names, seconds)


def _largest(models: dict, database: Path, names: list[str], seconds: dict) -> SfmResult:
    empty = SfmResult(database, names, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), {},
                      len(models), None, None, {}, seconds)
    if not models:
        return empty
    model = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))
    ids = np.array(sorted(model.points3D), dtype=np.int64)
    points = np.array([model.points3D[i].xyz for i in ids]).reshape(-1, 3)
    registered, image_points = {}, {}
    for image_id in model.reg_image_ids():
        image = model.images[image_id]
        pose = image.cam_from_world()
        registered[image.name] = (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
        image_points[image.name] = {i: int(p.point3D_id) for i, p in enumerate(image.points2D)
                                    if p.has_point3D()}
    camera = next(iter(model.cameras.values()))
    return SfmResult(database, names, points, ids, registered, len(models),
                     float(camera.mean_focal_length()), float(model.compute_mean_reprojection_error()),
                     image_points, seconds)


# -- COLMAP's feature tracks --------------------------------------------------------

@dataclass
class FeatureTracks:
    """Tracks of COLMAP's verified matches: for each, its photos and keypoints."""

    names: list[str]  # photo names, by database image id order
    image: np.ndarray  # (T,) photo index of each observation
    track: np.ndarray  # (T,) track index of each observation
    keypoint: np.ndarray  # (T,) keypoint index in its photo
    xy: np.ndarray  # (T, 2) pixels
    conflicting: int  # tracks dropped: two keypoints of one photo

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    def views_per_track(self) -> np.ndarray:
        return np.bincount(self.track, minlength=self.n_tracks)

    def views(self, min_points: int = 3) -> list[dict]:
        """One keypoint view per photo (tracks as ids), photos with fewer than
        ``min_points`` tracks left out."""
        out = []
        for k, name in enumerate(self.names):
            rows = np.flatnonzero(self.image == k)
            if len(rows) >= min_points:
                out.append({"name": name, "ids": self.track[rows], "xy": self.xy[rows]})
        return out


def database_tracks(database: Path) -> FeatureTracks:
    """Union-find over every verified inlier match of ``database``; a track
    holding two keypoints of one photo is inconsistent and dropped."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pycolmap = require_pycolmap()
    with pycolmap.Database.open(database) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        index = {im.image_id: k for k, im in enumerate(images)}
        keypoints = [np.asarray(db.read_keypoints(im.image_id))[:, :2] for im in images]
        pair_ids, geometries = db.read_two_view_geometries()
    offsets = np.concatenate([[0], np.cumsum([len(kp) for kp in keypoints])])
    edges = []
    for pair_id, geometry in zip(pair_ids, geometries):
        matches = np.asarray(geometry.inlier_matches).reshape(-1, 2)
        if not len(matches):
            continue
        a, b = (index[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
        edges.append(np.column_stack([offsets[a] + matches[:, 0], offsets[b] + matches[:, 1]]))
    names = [im.name for im in images]
    total = int(offsets[-1])
    if not edges:
        empty = np.zeros(0, dtype=np.int64)
        return FeatureTracks(names, empty, empty, empty, np.zeros((0, 2)), 0)
    edges = np.concatenate(edges)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    node = np.unique(edges)  # keypoints in some match
    image = np.searchsorted(offsets, node, side="right") - 1
    label = label[node]
    per_track = np.bincount(label)
    distinct = np.bincount(np.unique(label * len(images) + image) // len(images),
                           minlength=len(per_track))
    good = per_track == distinct  # no photo twice
    keep = good[label] & (per_track[label] >= 2)
    _, track = np.unique(label[keep], return_inverse=True)
    node, image = node[keep], image[keep]
    keypoint = node - offsets[image]
    xy = np.concatenate(keypoints)[node].astype(float)
    return FeatureTracks(names, image, track.astype(np.int64), keypoint, xy,
                         int(np.count_nonzero(~good & (per_track >= 2))))


def triangulated(tracks: FeatureTracks, sfm: SfmResult) -> dict[int, int]:
    """track -> the point3D of COLMAP's model that most of its keypoints went to."""
    votes: dict[int, dict[int, int]] = {}
    for t, k, kp in zip(tracks.track, tracks.image, tracks.keypoint):
        point = sfm.image_points.get(tracks.names[k], {}).get(int(kp))
        if point is not None:
            votes.setdefault(int(t), {}).setdefault(point, 0)
            votes[int(t)][point] += 1
    return {t: max(v, key=v.get) for t, v in votes.items()}


# -- model folders in and out -----------------------------------------------------

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
    pycolmap = require_pycolmap()
    folder = Path(folder)
    if model_files(folder) is None:
        _check_model_folder(folder)
        raise MpeError(f"{folder}: no COLMAP model (cameras, images and points3D as .bin or .txt)")
    if model_files(folder) == "bin":
        _check_binary_counts(folder)
    try:
        model = pycolmap.Reconstruction(folder)
    except Exception as exc:  # pycolmap raises RuntimeError/ValueError with COLMAP's check text
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MpeError(f"{folder}: cannot read the COLMAP model: {first}") from None
    if not model.cameras:
        raise MpeError(f"{folder}: the COLMAP model has no cameras")
    cameras = [model.cameras[i] for i in sorted(model.cameras)]
    focal = float(np.mean([c.mean_focal_length() for c in cameras]))
    centre = np.array([cameras[0].principal_point_x, cameras[0].principal_point_y], dtype=float)
    views = []
    for image_id in sorted(model.reg_image_ids()):
        image = model.images[image_id]
        rows = [(p.point3D_id, p.xy) for p in image.points2D if p.has_point3D()]
        if not rows:
            continue
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        xy = np.array([r[1] for r in rows], dtype=float)
        normalised = np.asarray(image.camera.cam_from_img(xy), dtype=float)
        views.append({"name": image.name, "ids": ids, "xy": focal * normalised[:, :2] + centre,
                      "principal_point": centre})
    if len(views) < 2:
        raise MpeError(f"{folder}: the COLMAP model has {len(views)} registered image(s) with "
                       "points; at least 2 are needed")
    return views


def _pinhole(camera: dict, principal_point, diameter: float):
    """(fx, fy, c, R, T) of a report camera: the pinhole itself, or an affine
    camera as a pinhole FAR diameters away that projects the same to 1 / FAR."""
    R = np.asarray(camera["rotation"], dtype=float)
    if "focal_px" in camera:
        f = float(camera["focal_px"])
        c = np.asarray(camera.get("principal_point", principal_point), dtype=float)
        return f, float(camera.get("focal_y_px", f)), c, R, np.asarray(camera["translation"], float)
    s = float(camera["scale"])
    depth = FAR * diameter
    t = (np.asarray(camera["translation_px"], dtype=float) - principal_point) / s
    return s * depth, s * depth, principal_point, R, np.array([t[0], t[1], depth])


def write_model(folder: str | Path, points: np.ndarray, ids: np.ndarray, views: list[dict],
                cameras: list[dict] | None, principal_point, image_size=None,
                dropped=()) -> list[str]:
    """``points`` as a COLMAP binary model in ``folder`` (created): a PINHOLE
    camera and a posed image per view with its keypoints, and each point with
    its track. Returns notes for what the model cannot say exactly.

    ``views`` are the keypoint views solved (names, ids, xy); ``cameras`` the
    report's cameras in the same order (None: points only, no images);
    ``dropped`` the (view name, id) pairs left out as wrong matches.
    """
    pycolmap = require_pycolmap()
    folder = Path(folder)
    model = pycolmap.Reconstruction()
    notes = []
    numeric = ids.dtype.kind in "iu" and len(ids) and ids.min() >= 0 and ids.max() < 2 ** 63 - 1
    point_id = (ids.astype(np.int64) + (1 if numeric and ids.min() == 0 else 0)) if numeric \
        else np.arange(1, len(ids) + 1)
    if not numeric or ids.min() == 0:
        notes.append("COLMAP point3D ids are positive integers: point i of the cloud has id "
                     + ("its id + 1" if numeric else "i + 1 (the order of the written cloud)"))
    row = {key: i for i, key in enumerate(ids.tolist())}
    tracks: dict[int, list] = {}
    if cameras is not None:
        diameter = float(np.linalg.norm(np.ptp(points, axis=0))) or 1.0
        c = np.asarray(principal_point, dtype=float)
        width, height = image_size or np.ceil(2 * c).astype(int)
        if any("focal_px" not in cam for cam in cameras):
            notes.append(f"COLMAP has no affine camera: each view is written as a pinhole "
                         f"{FAR:g} cloud diameters away, which projects like it to 1/{FAR:g}")
        skip = {(str(v), str(i)) for v, i in dropped}
        for k, (view, camera) in enumerate(zip(views, cameras), start=1):
            fx, fy, centre, R, T = _pinhole(camera, c, diameter)
            model.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(
                k, "PINHOLE", fx, int(width), int(height)))
            model.cameras[k].params = [fx, fy, centre[0], centre[1]]
            name = str(view.get("name", k - 1))
            keep = [j for j, i in enumerate(view["ids"]) if (name, str(i)) not in skip]
            xy = np.asarray(view["xy"], dtype=float)[keep]
            image = pycolmap.Image(name=name if "." in name else f"{name}.png",
                                   keypoints=xy, camera_id=k, image_id=k)
            model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.column_stack([R, T])))
            for j, i in enumerate(np.asarray(view["ids"])[keep].tolist()):
                if i in row:  # a point left out (unplaced) keeps its keypoint, not a track
                    tracks.setdefault(row[i], []).append(pycolmap.TrackElement(k, j))
    for i, (p, pid) in enumerate(zip(points, point_id)):
        point = pycolmap.Point3D()
        point.xyz = p
        point.track = pycolmap.Track(tracks.get(i, []))
        model.add_point3D_with_id(int(pid), point)
        for element in tracks.get(i, []):
            model.images[element.image_id].set_point3D_for_point2D(element.point2D_idx, int(pid))
    folder.mkdir(parents=True, exist_ok=True)
    model.write(folder)
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


def _report_camera(camera: dict) -> dict:
    """A report camera with its intrinsics read off its matrix: P = K [R | T]."""
    P = np.asarray(camera["P"], dtype=float)
    if "rotation" not in camera:  # known 3x4 matrices: K R by RQ, signs made positive
        from scipy.linalg import rq

        K, R = rq(P[:, :3])
        signs = np.sign(np.diag(K))
        K, R = K * signs, signs[:, None] * R
        T = np.linalg.solve(K, P[:, 3])
        if np.linalg.det(R) < 0:
            R, T = -R, -T
        K = K / K[2, 2]
        return {"focal_px": float(K[0, 0]), "focal_y_px": float(K[1, 1]), "rotation": R.tolist(),
                "translation": T.tolist(), "principal_point": K[:2, 2].tolist()}
    if "focal_px" in camera:
        K = P[:, :3] @ np.asarray(camera["rotation"], dtype=float).T
        return {**camera, "principal_point": (K[:2, 2] / K[2, 2]).tolist()}
    return camera


def write_model_folder(folder: Path, problem, result) -> list[str]:
    """The solved cloud of ``mpe3d reconstruct`` as a COLMAP model in ``folder``
    (its PLY is written beside by the caller); returns notes for the report."""
    obs, ids = problem.observations, problem.ids
    views = [{"name": name, "ids": ids[view.ids], "xy": view.coordinates}
             for name, view in zip(problem.view_names, obs.views)]
    report = result.report
    if report.get("objective") != "reprojection" or any(v["xy"] is None for v in views):
        cameras, centre = None, np.zeros(2)
        notes = ["the COLMAP model holds the points only: distance matrices give no keypoints "
                 "and no pinhole cameras"]
    else:
        cameras = [_report_camera(c) for c in report["cameras"]]
        centre = np.asarray(cameras[0].get("principal_point") or problem.principal_point
                            or (0.0, 0.0), dtype=float)
        notes = []
    dropped = [(d["view"], d["point"]) for d in report.get("dropped", {}).get("observations", [])]
    placed = ~np.isin(ids, np.asarray(report.get("unplaced", {}).get("ids", []), dtype=ids.dtype))
    return notes + write_model(folder, result.points[placed], ids[placed], views, cameras, centre,
                               None, dropped)
