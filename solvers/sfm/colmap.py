"""COLMAP through pycolmap: the one module of mpe3d that calls it.

Everything else asks COLMAP through the small functions here and gets plain
numbers back (numpy arrays and the dataclasses below), never a pycolmap
object, so that a pycolmap release that renames a call is mended here alone.
Each call turns COLMAP's failures into one line: :class:`~mpe3d.errors.MpeError`
(exit 2) when the input is at fault, :class:`~mpe3d.errors.MachineError`
(exit 3) when the machine is (no space left, a folder that cannot be
written); COLMAP's own log is silenced.

Repeatability: every random choice of COLMAP that pycolmap exposes takes
the caller's ``seed`` (RANSAC in verification and estimators, either
mapper's ``random_seed``, pycolmap's global seed). Extraction, matching and
verification repeat bit for bit on any thread count, once the photos are
numbered in name order (:func:`_in_name_order`). The mappers do not:
their solves (Ceres) sum in thread order, and a mapper's choices amplify the
last digits, so on two threads one seed gave 9, 10 or 12 of 12 views
registered from run to run. The mappers therefore always run on one thread
(on two cores, about a fifth more mapping time: docs/methods/colmap.md).

One module for all of it, past 500 lines (tests/test_architecture.py says
why): one place calls pycolmap, and a test holds every other module to that;
its parts (cameras, databases, extraction and matching, mapping, models,
estimators) are each short and share the error handling and the camera
conversions.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from mpe3d.errors import MachineError, MpeError, first_line

EXHAUSTIVE_UP_TO = 50  # photos; beyond, matching pairs each photo with its path neighbours
SEQUENTIAL_OVERLAP = 10  # neighbours on each side of a photo along the path
MIN_REGISTERED = 2  # views a model needs to be one
# What a photo's features and a pair's matches take in a database (a SIFT
# descriptor's 128 bytes and a keypoint's 6 floats; a match's two ids, twice
# when the verification keeps its inliers), and a margin for SQLite's pages
# and journal: 11 real photos at 8,192 features made 21 MB against 20.7 MB
# before the margin. The margin matters: COLMAP's extractor and matcher write
# from worker threads, and a full disk there aborts the whole process
# (SIGABRT from std::terminate) before any error can be caught.
FEATURE_BYTES = 128 + 6 * 4
MATCH_BYTES = 2 * 4
SCRATCH_MARGIN = 1.5
NO_SPACE = ("no space left", "disk is full", "disk full", "quota exceeded")


# -- pycolmap and its errors -----------------------------------------------------------

def _pycolmap():
    """pycolmap, or one line saying how to get it; COLMAP's log silenced."""
    try:
        import pycolmap
    except ImportError:
        raise MpeError("COLMAP support needs pycolmap: pip install pycolmap") from None
    logging = getattr(pycolmap, "logging", None)
    if logging is not None and hasattr(logging, "minloglevel"):
        logging.minloglevel = 3  # none: a failure is said in our one line
    return pycolmap


def _seed(seed: int) -> int:
    """A seed COLMAP takes (its RANSAC's is an int32): any integer >= 0, folded."""
    return int(seed) % 2 ** 31


def version() -> str:
    pycolmap = _pycolmap()
    return f"pycolmap {pycolmap.__version__} ({pycolmap.COLMAP_version})"


@contextlib.contextmanager
def _asked(what: str, culprit) -> Iterator[None]:
    """COLMAP's failures inside the block as one line: ``culprit: cannot what: reason``."""
    try:
        yield
    except MpeError:
        raise
    except (RuntimeError, ValueError, OSError, LookupError) as exc:
        reason = first_line(exc, 200)
        kind = MachineError if any(s in reason.lower() for s in NO_SPACE) else MpeError
        raise kind(f"{culprit}: COLMAP cannot {what}: {reason}") from None


# -- scratch folders ----------------------------------------------------------------

def scratch_bytes(photos: int, max_features: int, pairs: int, verified: bool) -> int:
    """What a database of ``photos`` and ``pairs`` matched pairs takes, at most:
    its features twice (numbered in name order, they are copied once)."""
    return int(SCRATCH_MARGIN * (2 * photos * max_features * FEATURE_BYTES
                                 + pairs * max_features * MATCH_BYTES * (2 if verified else 1)))


def _named(where: Path, given: bool) -> str:
    return f"--scratch {where}" if given else f"the temporary folder {where} (no --scratch given)"


def check_space(where: Path, need: int, given: bool = True) -> None:
    """One line (exit 3) when ``where`` (``given`` by the user, or the system's
    temporary folder) has less than ``need`` bytes free."""
    free = shutil.disk_usage(where).free
    if free < need:
        raise MachineError(f"{_named(where, given)}: {free / 2**20:.0f} MB free, about {need / 2**20:.0f} MB "
                           "needed for the features and matches (give --scratch a folder on a larger disk)")


@contextlib.contextmanager
def scratch(parent: Path | None, need: int, prefix: str = "mpe3d-colmap-") -> Iterator[Path]:
    """A new folder under ``parent`` (None: the system's temporary folder),
    removed afterwards; refused in one line (exit 3) when ``parent`` cannot be
    written or has less than ``need`` bytes free."""
    where = Path(parent) if parent is not None else Path(tempfile.gettempdir())
    if not where.is_dir():
        raise MpeError(f"--scratch {where}: no such folder")
    check_space(where, need, given=parent is not None)
    try:
        folder = tempfile.TemporaryDirectory(prefix=prefix, dir=where)
    except OSError as exc:
        raise MachineError(f"{_named(where, parent is not None)}: cannot write there ({exc.strerror or exc})") \
            from None
    with folder as name:
        yield Path(name)


# -- cameras ----------------------------------------------------------------------

@dataclass(frozen=True)
class Camera:
    """A COLMAP camera as plain numbers: its model's name and parameters."""

    model: str  # COLMAP's name: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, OPENCV, ...
    width: int
    height: int
    params: tuple[float, ...]
    prior_focal: bool = False  # the focal length is known (EXIF, a calibration), not guessed
    camera_id: int = 1

    @property
    def focal(self) -> float:
        """The mean focal length in pixels (fx and fy's mean for two)."""
        return float(self._colmap().mean_focal_length())

    @property
    def principal_point(self) -> np.ndarray:
        c = self._colmap()
        return np.array([c.principal_point_x, c.principal_point_y], dtype=float)

    @property
    def is_pinhole(self) -> bool:
        """No distortion and square pixels: keypoints need no conversion."""
        return self.model in ("SIMPLE_PINHOLE",) or (
            self.model == "PINHOLE" and self.params[0] == self.params[1]) or (
            self.model in ("SIMPLE_RADIAL", "RADIAL") and not any(self.params[3:]))

    def _colmap(self):
        pycolmap = _pycolmap()
        with _asked("read the camera", f"camera {self.camera_id} ({self.model})"):
            camera = pycolmap.Camera(model=self.model, width=self.width, height=self.height,
                                     params=list(self.params))
            camera.has_prior_focal_length = self.prior_focal
        return camera

    def check(self, culprit: str) -> "Camera":
        """This camera, or one line naming it when mpe3d cannot model it."""
        where = f"{culprit}: camera {self.camera_id} ({self.model}, {self.width}x{self.height})"
        if self.width <= 0 or self.height <= 0:
            raise MpeError(f"{where}: an image size of 0 pixels")
        camera = self._colmap()
        if camera.is_spherical():
            raise MpeError(f"{where}: a spherical camera; mpe3d models cameras that project onto a plane")
        if not camera.verify_params() or not np.all(np.isfinite(self.params)) or self.focal <= 0:
            raise MpeError(f"{where}: parameters {list(self.params)} are not its model's")
        return self

    def to_pinhole(self, xy: np.ndarray, focal: float, centre) -> np.ndarray:
        """``xy`` (n, 2) through this camera to the image of a pinhole of
        ``focal`` and principal point ``centre``: its lens, aspect and own
        principal point taken out, by its model's parameters."""
        normalised = np.asarray(self._colmap().cam_from_img(np.asarray(xy, dtype=float)), dtype=float)
        if not np.all(np.isfinite(normalised)):  # its undistortion found no ray for some keypoint
            raise MpeError(f"camera {self.camera_id} ({self.model}, parameters {list(self.params)}): its lens "
                           "cannot be taken out of every keypoint (undistortion does not converge)")
        return focal * normalised[:, :2] + np.asarray(centre, dtype=float)


def _camera(pc, camera_id=None) -> Camera:
    return Camera(pc.model.name, int(pc.width), int(pc.height), tuple(float(v) for v in pc.params),
                  bool(pc.has_prior_focal_length), int(pc.camera_id if camera_id is None else camera_id))


def keypoint_box(z: np.ndarray, centre) -> tuple[int, int]:
    """(width, height) of an image that holds every keypoint ``z`` round the
    principal point ``centre``: keypoints may be centred on it (Bundler's and
    BAL's are), or in pixels from the corner."""
    width, height = np.ceil(2 * np.max(np.abs(np.asarray(z, dtype=float) - centre), axis=0)).astype(int) + 1
    return int(width), int(height)


def simple_camera(model: str, width: int, height: int, focal: float, centre, prior: bool = False,
                  camera_id: int = 1) -> Camera:
    """A one-focal camera of ``model`` (SIMPLE_PINHOLE, SIMPLE_RADIAL: k = 0)."""
    extra = (0.0,) if model == "SIMPLE_RADIAL" else ()
    return Camera(model, int(width), int(height), (float(focal), float(centre[0]), float(centre[1])) + extra,
                  prior, camera_id)


# -- databases ------------------------------------------------------------------------

@dataclass
class Database:
    """A COLMAP database's images, their cameras, keypoints and matches."""

    names: list[str]  # by image id
    camera_of: np.ndarray  # (I,) each image's camera id
    cameras: dict[int, Camera]
    keypoints: list[np.ndarray]  # (n_i, 2) pixels, per image
    pairs: np.ndarray  # (M, 2) image indices of each matched pair
    matches: list[np.ndarray]  # (m, 2) keypoint indices, per pair


COLMAP_TABLES = ("cameras", "images", "keypoints")  # what a file must hold to be read as COLMAP's database


def _check_tables(path: Path) -> None:
    """One line unless ``path`` holds COLMAP's tables, looked at read-only:
    COLMAP writes its schema into any SQLite file it opens."""
    import sqlite3

    try:
        with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
            tables = {row[0] for row in db.execute("select name from sqlite_master where type='table'")}
    except sqlite3.Error as exc:
        raise MpeError(f"{path}: not a readable SQLite file ({first_line(exc)})") from None
    missing = [t for t in COLMAP_TABLES if t not in tables]
    if missing:
        raise MpeError(f"{path}: not a COLMAP database (no {', '.join(missing)} table)")


def _check_matches(path: Path, names, keypoints, pairs, matches) -> None:
    """One line naming the pair whose matches point past a photo's keypoints
    (a stale database: the keypoints extracted again, the matches not)."""
    for (a, b), pair in zip(pairs, matches):
        if len(pair) and (pair[:, 0].max() >= len(keypoints[a]) or pair[:, 1].max() >= len(keypoints[b])):
            raise MpeError(f"{path}: the matches of {names[a]} and {names[b]} point past their keypoints "
                           "(run the matcher again)")


def read_database(path: Path, matches: str) -> Database:
    """``path``'s images, cameras, keypoints and its ``matches`` (raw: the
    matcher's; verified: the inliers of its geometric verification)."""
    pycolmap = _pycolmap()
    _check_tables(path)
    with _asked("read it as a database", path), pycolmap.Database.open(str(path)) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        cameras = {int(c.camera_id): _camera(c) for c in db.read_all_cameras()}
        keypoints = [np.asarray(db.read_keypoints(im.image_id))[:, :2].reshape(-1, 2).astype(float)
                     for im in images]
        if matches == "raw":
            pair_ids, found = db.read_all_matches()
        else:
            pair_ids, geometries = db.read_two_view_geometries()
            found = [geometry.inlier_matches for geometry in geometries]
        index = {im.image_id: k for k, im in enumerate(images)}
        pairs = np.array([[index[i] for i in pycolmap.pair_id_to_image_pair(p)] for p in pair_ids],
                         dtype=np.int64).reshape(-1, 2)
    names, found = [im.name for im in images], [np.asarray(m).reshape(-1, 2).astype(np.int64) for m in found]
    _check_matches(path, names, keypoints, pairs, found)
    return Database(names, np.array([im.camera_id for im in images], dtype=np.int64), cameras, keypoints, pairs,
                    found)


def write_database(path: Path, names: list[str], cameras: list[Camera], camera_of: np.ndarray,
                   keypoints: list[np.ndarray], pairs: np.ndarray, matches: list[np.ndarray]) -> None:
    """A database COLMAP's verification and mapper take: ``cameras`` (each with
    a rig), an image and frame per name on its camera ``camera_of[k]`` (an index
    into ``cameras``), its keypoints, and the raw ``matches`` of each pair."""
    pycolmap = _pycolmap()
    with _asked("write its database", path), pycolmap.Database.open(str(path)) as db:
        sensors = []
        for camera in cameras:
            pc = camera._colmap()
            pc.camera_id = db.write_camera(pc)
            rig = pycolmap.Rig()
            rig.add_ref_sensor(pc.sensor_id)
            sensors.append((pc, db.write_rig(rig)))
        image_ids = []
        for k, name in enumerate(names):
            pc, rig_id = sensors[int(camera_of[k])]
            image_id = db.write_image(pycolmap.Image(name=name, camera_id=pc.camera_id))
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(pycolmap.data_t(pc.sensor_id, image_id))
            image = db.read_image(image_id)
            image.frame_id = db.write_frame(frame)
            db.update_image(image)
            db.write_keypoints(image_id, np.asarray(keypoints[k], dtype=np.float32))
            image_ids.append(image_id)
        for (a, b), pair in zip(pairs, matches):
            db.write_matches(image_ids[a], image_ids[b], np.asarray(pair).astype(np.uint32))


# -- extraction and matching -----------------------------------------------------------

def matching_for(count: int, matching: str = "auto") -> str:
    if matching != "auto":
        return matching
    return "exhaustive" if count <= EXHAUSTIVE_UP_TO else "sequential"


def matched_pairs(count: int, matching: str = "auto") -> int:
    """The pairs the matcher compares among ``count`` photos."""
    if matching_for(count, matching) == "exhaustive":
        return count * (count - 1) // 2
    return count * 2 * SEQUENTIAL_OVERLAP  # the neighbours, and as many at quadratic steps (COLMAP's default)


def extract_and_match(database: Path, image_dir: Path, names: list[str], *, camera: Camera | None = None,
                      matching: str = "auto", threads: int = 1, max_features: int = 8192,
                      verify: bool = True, seed: int = 0) -> dict[str, float]:
    """SIFT on ``names`` and their matches into ``database``, each pair's
    geometrically verified too unless ``verify`` is False (raw matches need
    none, and it is most of the matching's time: 250 photos, 7.1 s with it,
    0.8 s without). ``camera``: one camera for every photo, as given (its
    model and parameters); None: a SIMPLE_RADIAL camera per image size and
    EXIF focal length, as COLMAP's extractor makes them. Returns the seconds
    of each step."""
    pycolmap = _pycolmap()
    pycolmap.set_random_seed(_seed(seed))
    seconds = {}
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera.model if camera is not None else "SIMPLE_RADIAL"
    reader.camera_params = ",".join(str(float(v)) for v in camera.params) if camera is not None else ""
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = max_features
    mode = pycolmap.CameraMode.SINGLE if camera is not None else pycolmap.CameraMode.AUTO
    with _asked("extract features", image_dir):
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
    with _asked("number the photos in name order", database):
        _in_name_order(database)
    seconds["extract_s"] = time.perf_counter() - start
    start = time.perf_counter()
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    options.skip_geometric_verification = not verify
    geometry = pycolmap.TwoViewGeometryOptions()
    geometry.ransac.random_seed = _seed(seed)
    with _asked("match features", image_dir):
        if matching_for(len(names), matching) == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=options, verification_options=geometry,
                                      device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = SEQUENTIAL_OVERLAP
            pairing.loop_detection = False  # needs a vocabulary tree file
            pycolmap.match_sequential(database, matching_options=options, pairing_options=pairing,
                                      verification_options=geometry, device=pycolmap.Device.cpu)
    seconds["match_s"] = time.perf_counter() - start
    return seconds


def _in_name_order(database: Path) -> None:
    """Number the cameras, rigs, frames and images of a freshly extracted
    ``database`` in the photos' name order. The extractor's threads write each
    photo when they finish it, so its numbers vary from run to run; and they
    order every pair of a match (a < b), which RANSAC samples by, and the
    views. Renumbered, verification and the views repeat on any thread count.
    The photos are copied one at a time into a new file beside it, which then
    replaces it (a camera no photo uses is left out). A database of rigs (a
    frame of several images) is left as written."""
    pycolmap = _pycolmap()
    ordered = database.with_name(database.name + ".ordered")
    with pycolmap.Database.open(str(database)) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.name)
        first_use = list(dict.fromkeys(im.camera_id for im in images))
        if ([im.image_id for im in images] == list(range(1, len(images) + 1))
                and first_use == list(range(1, db.num_cameras() + 1))
                or any(f.num_data_ids() != 1 for f in db.read_all_frames())):
            return
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        priors = {p.corr_data_id.id: p for p in db.read_all_pose_priors()}
        ordered.unlink(missing_ok=True)
        with pycolmap.Database.open(str(ordered)) as out, pycolmap.DatabaseTransaction(out):
            sensors = {}
            for old_id in first_use:
                camera, rig = cameras[old_id], pycolmap.Rig()
                camera.camera_id = out.write_camera(camera)
                rig.add_ref_sensor(camera.sensor_id)
                sensors[old_id] = (camera, out.write_rig(rig))
            for image in images:
                camera, rig_id = sensors[image.camera_id]
                image_id = out.write_image(pycolmap.Image(name=image.name, camera_id=camera.camera_id))
                frame = pycolmap.Frame()
                frame.rig_id = rig_id
                frame.add_data_id(pycolmap.data_t(camera.sensor_id, image_id))
                out.write_frame(frame)
                out.write_keypoints(image_id, db.read_keypoints(image.image_id))
                out.write_descriptors(image_id, db.read_descriptors(image.image_id))
                prior = priors.get(image.image_id)
                if prior is not None:
                    prior.corr_data_id = pycolmap.data_t(camera.sensor_id, image_id)
                    out.write_pose_prior(prior)
    ordered.replace(database)


def verify_matches(database: Path, *, threads: int = 1, seed: int = 0) -> None:
    """COLMAP's two-view geometric verification (F, E or H by RANSAC) of every raw match."""
    pycolmap = _pycolmap()
    pycolmap.set_random_seed(_seed(seed))
    verifier = pycolmap.GeometricVerifierOptions()
    verifier.num_threads = threads
    geometry = pycolmap.TwoViewGeometryOptions()
    geometry.ransac.random_seed = _seed(seed)
    with _asked("verify the matches", database):
        pycolmap.geometric_verification(str(database), verifier_options=verifier,
                                        two_view_geometry_options=geometry)


# -- mapping and models ------------------------------------------------------------------

@dataclass
class ModelImage:
    """A registered image of a model: its pose and its keypoints' 3D points."""

    camera_id: int
    rotation: np.ndarray  # (3, 3) world -> camera
    translation: np.ndarray  # (3,)
    xy: np.ndarray  # (n, 2) keypoints, pixels
    point3d: np.ndarray  # (n,) each keypoint's point3D id, -1 for none


@dataclass
class Model:
    """A sparse model as plain numbers (the largest, when the mapper made several)."""

    cameras: dict[int, Camera]
    images: dict[str, ModelImage]  # registered images, by name
    point_ids: np.ndarray  # (P,)
    points: np.ndarray  # (P, 3)
    models: int = 1  # how many separate models the mapper made
    reprojection_px: float = float("nan")  # mean reprojection error
    seconds: dict[str, float] = field(default_factory=dict)

    def point_of(self, ids: np.ndarray) -> np.ndarray:
        """(n, 3) the points of point3D ``ids``."""
        order = np.argsort(self.point_ids)
        return self.points[order[np.searchsorted(self.point_ids, ids, sorter=order)]]


def _model(reconstruction, models: int = 1, seconds=None) -> Model:
    images = {}
    for image_id in sorted(reconstruction.reg_image_ids()):
        image = reconstruction.images[image_id]
        pose = image.cam_from_world()
        points2d = image.points2D
        images[image.name] = ModelImage(
            int(image.camera_id), np.asarray(pose.rotation.matrix(), dtype=float),
            np.asarray(pose.translation, dtype=float),
            np.array([p.xy for p in points2d], dtype=float).reshape(-1, 2),
            np.array([p.point3D_id if p.has_point3D() else -1 for p in points2d], dtype=np.int64))
    ids = np.array(sorted(reconstruction.points3D), dtype=np.int64)
    points = np.array([reconstruction.points3D[i].xyz for i in ids], dtype=float).reshape(-1, 3)
    cameras = {int(i): _camera(c, i) for i, c in reconstruction.cameras.items()}
    error = float(reconstruction.compute_mean_reprojection_error()) if len(ids) else float("nan")
    return Model(cameras, images, ids, points, models, error, dict(seconds or {}))


def _largest(mapper, options, database: Path, image_dir: Path, out: Path, seed: int) -> Model | None:
    """``mapper`` (a pycolmap mapping call) on ``database`` with ``options``,
    seeded, on one thread (a seed must repeat a run: module docstring); its
    largest model (most registered images, then most points), or None when it
    made none. ``seconds`` holds the mapping's time."""
    pycolmap = _pycolmap()
    pycolmap.set_random_seed(_seed(seed))
    options.num_threads = 1
    options.random_seed = _seed(seed)
    start = time.perf_counter()
    with _asked("map the photos", database):
        Path(out).mkdir(parents=True, exist_ok=True)
        models = mapper(str(database), str(image_dir), str(out), options=options)
    seconds = {"map_s": time.perf_counter() - start}
    best = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()), default=None)
    return None if best is None else _model(best, len(models), seconds)


def incremental_mapping(database: Path, image_dir: Path, out: Path, *, seed: int = 0) -> Model | None:
    """COLMAP's incremental mapper on ``database`` (its models written under
    ``out``); its largest model, or None when it made none (a model of fewer
    than :data:`MIN_REGISTERED` images is none to a caller that needs one).
    ``seconds`` holds the mapping's time."""
    pycolmap = _pycolmap()
    options = pycolmap.IncrementalPipelineOptions()
    options.extract_colors = False  # no photo is read again: a point's colour is no use to a score
    return _largest(pycolmap.incremental_mapping, options, database, image_dir, out, seed)


def global_mapping(database: Path, image_dir: Path, out: Path, *, seed: int = 0) -> Model | None:
    """COLMAP's global mapper (GLOMAP's: rotation averaging, then global
    positioning of cameras and points together, then bundle adjustment) on
    the verified matches of ``database``, as :func:`incremental_mapping`.
    Its pipeline hands the one thread and ``seed`` on to every stage (rotation
    averaging, positioning, bundle adjustment, re-triangulation). It keeps
    models of :data:`MIN_REGISTERED` images or more, as the incremental one
    can, not only of its default three. ``image_dir`` is not read: the
    mapper reads the photos again for its points' colours when it finds them
    (it has no option against that), so it is shown ``out``, where none is."""
    pycolmap = _pycolmap()
    options = pycolmap.GlobalPipelineOptions()
    options.min_model_size = MIN_REGISTERED
    Path(out).mkdir(parents=True, exist_ok=True)
    return _largest(pycolmap.global_mapping, options, database, out, out, seed)


def read_model(folder: Path) -> Model:
    """A model folder (``cameras``, ``images``, ``points3D``, binary or text);
    one of poses alone (no ``points3D``, as a hand-made reference often is)
    is read as one without points, which COLMAP's reader refuses."""
    pycolmap = _pycolmap()
    folder = Path(folder)
    with _asked("read the model", folder):
        if any((folder / f"points3D{ext}").is_file() for ext in (".bin", ".txt")):
            return _model(pycolmap.Reconstruction(folder))
        with tempfile.TemporaryDirectory(prefix="mpe3d-model-") as copy:
            for part in folder.iterdir():
                if part.is_file():
                    shutil.copy2(part, Path(copy) / part.name)
            binary = (folder / "images.bin").is_file()
            (Path(copy) / ("points3D.bin" if binary else "points3D.txt")).write_bytes(b"\0" * 8 if binary else b"")
            return _model(pycolmap.Reconstruction(copy))


@dataclass
class PosedImage:
    """An image to write into a model: its camera, pose and keypoints."""

    name: str
    camera: Camera
    rotation: np.ndarray
    translation: np.ndarray
    xy: np.ndarray  # (n, 2)


def write_model(folder: Path, images: list[PosedImage], point_ids: np.ndarray, points: np.ndarray,
                tracks: dict[int, list[tuple[int, int]]]) -> None:
    """A binary model COLMAP's GUI opens: each image (ids from 1, its camera
    with the same id), each point with its track ``tracks[row]`` of
    (image index, keypoint index)."""
    pycolmap = _pycolmap()
    model = pycolmap.Reconstruction()
    with _asked("write the model", folder):
        for k, image in enumerate(images, start=1):
            camera = image.camera._colmap()
            camera.camera_id = k
            model.add_camera_with_trivial_rig(camera)
            posed = pycolmap.Image(name=image.name, keypoints=np.asarray(image.xy, dtype=float), camera_id=k,
                                   image_id=k)
            model.add_image_with_trivial_frame(
                posed, pycolmap.Rigid3d(np.column_stack([image.rotation, image.translation])))
        for row, (xyz, pid) in enumerate(zip(points, point_ids)):
            elements = [pycolmap.TrackElement(k + 1, j) for k, j in tracks.get(row, [])]
            point = pycolmap.Point3D()
            point.xyz = xyz
            point.track = pycolmap.Track(elements)
            model.add_point3D_with_id(int(pid), point)
            for element in elements:
                model.images[element.image_id].set_point3D_for_point2D(element.point2D_idx, int(pid))
        folder.mkdir(parents=True, exist_ok=True)
        model.write(folder)


# -- robust estimators ----------------------------------------------------------------

def _ransac(options, max_error: float, seed: int, trials: int):
    options.max_error = max_error
    options.random_seed = _seed(seed)
    options.max_num_trials = trials
    return options


def essential_matrix(za: np.ndarray, zb: np.ndarray, camera: Camera, *, max_error: float, seed: int,
                     trials: int):
    """The essential matrix of matches (za, zb) of two views of ``camera`` by
    LO-RANSAC: (E, R, t of the second view, inliers) or None."""
    pycolmap = _pycolmap()
    pc = camera._colmap()
    ransac = _ransac(pycolmap.RANSACOptions(), max_error, seed, trials)
    with _asked("estimate an essential matrix", "tracks"):
        found = pycolmap.estimate_essential_matrix(za, zb, pc, pc, ransac)
    if found is None:
        return None
    pose = found["cam2_from_cam1"]
    return (np.asarray(found["E"]), np.asarray(pose.rotation.matrix()), np.asarray(pose.translation),
            int(found["num_inliers"]))


def absolute_pose(z: np.ndarray, X: np.ndarray, camera: Camera, *, max_error: float, seed: int,
                  trials: int):
    """A view's pose from its keypoints ``z`` of points ``X`` by P3P in
    LO-RANSAC, refined: (R, t, inlier mask, inlier count) or None."""
    pycolmap = _pycolmap()
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    _ransac(estimation.ransac, max_error, seed, trials)
    with _asked("estimate a pose", "tracks"):
        found = pycolmap.estimate_and_refine_absolute_pose(z, X, camera._colmap(), estimation)
    if found is None:
        return None
    pose = found["cam_from_world"]
    return (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation),
            np.asarray(found["inlier_mask"], dtype=bool), int(found["num_inliers"]))
