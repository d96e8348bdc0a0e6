"""Photos and COLMAP databases in: SIFT features, matches and their tracks, by pycolmap.

* :func:`extract_and_match`: SIFT keypoints of each photo and their matches
  (exhaustive up to :data:`EXHAUSTIVE_UP_TO` photos, sequential along the
  path beyond), into a COLMAP database;
* :func:`match_tracks`: a database's matches joined into tracks (union-find
  over the matched keypoints), the matcher's raw matches or those its
  geometric verification kept; a track that holds two keypoints of one
  photo is inconsistent and dropped;
* :func:`read_photos` and :func:`read_database`: either as keypoint views
  for :func:`mpe3d.harness.userdata.reconstruct.reconstruct`, each with the
  photos' principal point, size and, when it is plausible, EXIF focal length.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.options import MATCHES, Interval
from mpe3d.solvers.sfm.colmap_link import require_pycolmap

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")
EXHAUSTIVE_UP_TO = 50  # photos; beyond, matching pairs each photo with its path neighbours
SEQUENTIAL_OVERLAP = 10  # neighbours on each side of a photo along the path
# An EXIF focal length is trusted between these multiples of the larger image
# side (fields of view of about 14 to 118 degrees); beyond, it is a camera's
# lie or a resized photo's stale tag (3,767 px for a 640-px image).
PLAUSIBLE_FOCAL = Interval(float, 0.3, 4.0)
MIN_TRACKS = 3  # tracks a photo must hold to be a view
SQLITE_HEADER = b"SQLite format 3\x00"


@dataclass
class FeatureTracks:
    """Tracks of a database's matches: for each observation, its photo and keypoint."""

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

    def views(self, min_points: int = MIN_TRACKS) -> list[dict]:
        """One keypoint view per photo (tracks as ids), photos with fewer than
        ``min_points`` tracks left out."""
        out = []
        for k, name in enumerate(self.names):
            rows = np.flatnonzero(self.image == k)
            if len(rows) >= min_points:
                out.append({"name": name, "ids": self.track[rows], "xy": self.xy[rows]})
        return out


def photo_names(folder: Path) -> list[str]:
    """The photos of ``folder`` (not its subfolders), by name."""
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def looks_like_database(path: Path) -> bool:
    """A COLMAP database is an SQLite file (any name; COLMAP's is ``database.db``)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(SQLITE_HEADER)) == SQLITE_HEADER
    except OSError:
        return False


def matching_for(count: int, matching: str = "auto") -> str:
    if matching != "auto":
        return matching
    return "exhaustive" if count <= EXHAUSTIVE_UP_TO else "sequential"


def extract_and_match(database: Path, image_dir: Path, names: list[str], *, camera_model: str,
                      camera_params: str = "", matching: str = "auto", threads: int = 1,
                      max_features: int = 8192, verify: bool = True) -> dict[str, float]:
    """SIFT on ``names`` (one shared camera) and their matches into ``database``,
    each pair's geometrically verified too unless ``verify`` is False (raw
    matches need none, and it is most of the matching's time: 250 photos,
    7.1 s with it, 0.8 s without); returns the seconds of each step."""
    pycolmap = require_pycolmap()
    seconds = {}
    start = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = max_features
    pycolmap.extract_features(database, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["extract_s"] = time.perf_counter() - start
    start = time.perf_counter()
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    options.skip_geometric_verification = not verify
    if matching_for(len(names), matching) == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=options, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.loop_detection = False  # needs a vocabulary tree file
        pycolmap.match_sequential(database, matching_options=options, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    seconds["match_s"] = time.perf_counter() - start
    return seconds


def match_tracks(database: Path, matches: str = "verified") -> FeatureTracks:
    """Union-find over every match of ``database`` (``matches``: the matcher's
    raw ones, or the inliers of its geometric verification)."""
    MATCHES.check("matches", matches)
    pycolmap = require_pycolmap()
    with pycolmap.Database.open(str(database)) as db:
        images = sorted(db.read_all_images(), key=lambda im: im.image_id)
        index = {im.image_id: k for k, im in enumerate(images)}
        keypoints = [np.asarray(db.read_keypoints(im.image_id))[:, :2].reshape(-1, 2) for im in images]
        if matches == "raw":
            pair_ids, found = db.read_all_matches()
        else:
            pair_ids, geometries = db.read_two_view_geometries()
            found = [geometry.inlier_matches for geometry in geometries]
    offsets = np.concatenate([[0], np.cumsum([len(kp) for kp in keypoints])]).astype(np.int64)
    edges = []
    for pair_id, pair in zip(pair_ids, found):
        pair = np.asarray(pair).reshape(-1, 2).astype(np.int64)
        if len(pair):
            a, b = (index[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
            edges.append(np.column_stack([offsets[a] + pair[:, 0], offsets[b] + pair[:, 1]]))
    names = [im.name for im in images]
    if not edges:
        empty = np.zeros(0, dtype=np.int64)
        return FeatureTracks(names, empty, empty, empty, np.zeros((0, 2)), 0)
    return _union(names, keypoints, offsets, np.concatenate(edges))


def _union(names, keypoints, offsets, edges) -> FeatureTracks:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    total = int(offsets[-1])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    node = np.unique(edges)  # keypoints in some match
    image = np.searchsorted(offsets, node, side="right") - 1
    label = label[node]
    per_track = np.bincount(label)
    distinct = np.bincount(np.unique(label * len(names) + image) // len(names), minlength=len(per_track))
    good = per_track == distinct  # no photo twice
    keep = good[label] & (per_track[label] >= 2)
    _, track = np.unique(label[keep], return_inverse=True)
    node, image = node[keep], image[keep]
    xy = np.concatenate(keypoints)[node].astype(float)
    return FeatureTracks(names, image, track.astype(np.int64), node - offsets[image], xy,
                         int(np.count_nonzero(~good & (per_track >= 2))))


def tied_views(views: list[dict]) -> list[dict]:
    """The largest group of ``views`` that shared tracks tie together (the
    rule of :func:`mpe3d.solvers.degenerate.check_geometry`), as COLMAP keeps
    its largest model: photos that no track links to the rest fix nothing."""
    from mpe3d.solvers.degenerate import SHARED_VARIABLE, view_groups

    n = 1 + max(int(v["ids"].max()) for v in views)
    alpha = np.zeros((len(views), n), dtype=np.int32)
    for k, view in enumerate(views):
        alpha[k, view["ids"]] = 1
    count, labels = view_groups(alpha @ alpha.T, SHARED_VARIABLE)
    largest = np.argmax(np.bincount(labels))
    return [v for v, label in zip(views, labels) if label == largest]


def _camera_facts(database: Path) -> dict:
    """The photos' shared principal point and size, and their EXIF focal
    length when it is plausible."""
    pycolmap = require_pycolmap()
    with pycolmap.Database.open(str(database)) as db:
        cameras = db.read_all_cameras()
    if not cameras:
        return {}
    camera = cameras[0]
    facts = {"principal_point": (float(camera.principal_point_x), float(camera.principal_point_y)),
             "image_size": (int(camera.width), int(camera.height))}
    ratio = float(camera.focal_length) / max(camera.width, camera.height)
    if camera.has_prior_focal_length and ratio in PLAUSIBLE_FOCAL:
        facts["focal_px"] = float(camera.focal_length)
    return facts


def read_database(path: str | Path, matches: str = "raw") -> list[dict]:
    """A COLMAP database's tracks as keypoint views (see the module's docstring)."""
    path = Path(path)
    MATCHES.check("matches", matches)
    try:
        tracks = match_tracks(path, matches)
    except (RuntimeError, ValueError) as exc:  # pycolmap's: not a COLMAP database
        raise MpeError(f"{path}: not a COLMAP database ({str(exc).splitlines()[0][:120]})") from None
    if not tracks.names:
        raise MpeError(f"{path}: the database holds no images")
    if not len(tracks.track):
        kind = "verified matches (run its geometric verification, or give --matches raw)" \
            if matches == "verified" else "matches (run a matcher on it: colmap exhaustive_matcher)"
        raise MpeError(f"{path}: the database holds no {kind}")
    views = tracks.views()
    if len(views) < 2:
        raise MpeError(f"{path}: {len(views)} of {len(tracks.names)} photos share {MIN_TRACKS} or more "
                       "tracks with the others; reconstruction needs 2")
    tied = tied_views(views)
    notes = [] if len(tied) == len(views) else [
        f"{len(views) - len(tied)} photo(s) share too few tracks with the largest group of "
        f"{len(tied)}: left out ({', '.join(v['name'] for v in views if all(v is not t for t in tied))[:200]})"]
    facts = _camera_facts(path)
    return [{**view, **facts, "notes": notes, "matches": matches} for view in tied]


def _check_photos(folder: Path, names: list[str]) -> tuple[int, int]:
    """Every photo readable and of one size; returns (width, height)."""
    from PIL import Image, UnidentifiedImageError

    if len(names) < 2:
        found = f"{len(names)} photo" + ("" if len(names) == 1 else "s")
        raise MpeError(f"{folder}: {found} ({', '.join(IMAGE_SUFFIXES)}); reconstruction needs 2 or more")
    sizes = {}
    for name in names:
        try:
            with Image.open(folder / name) as image:
                image.verify()
                sizes.setdefault(image.size, name)
        except (UnidentifiedImageError, OSError, SyntaxError) as exc:
            raise MpeError(f"{folder / name}: not a readable image ({exc.__class__.__name__})") from None
    if len(sizes) > 1:
        (a, first), (b, other) = list(sizes.items())[:2]
        raise MpeError(f"{folder}: photos of one camera and size are expected; {first} is "
                       f"{a[0]}x{a[1]}, {other} is {b[0]}x{b[1]}")
    return next(iter(sizes))


def read_photos(folder: str | Path, matches: str = "raw", *, threads: int | None = None,
                max_features: int = 8192) -> list[dict]:
    """A folder of photos as keypoint views: SIFT features, matches and tracks by pycolmap."""
    from mpe3d.solvers import threads as solver_threads

    folder = Path(folder)
    MATCHES.check("matches", matches)
    names = photo_names(folder)
    _check_photos(folder, names)
    with tempfile.TemporaryDirectory(prefix="mpe3d-photos-") as scratch:
        database = Path(scratch) / "database.db"
        # raw matches need no geometric verification; verified ones are its inliers
        extract_and_match(database, folder, names, camera_model="SIMPLE_RADIAL",
                          threads=threads or solver_threads.count(), max_features=max_features,
                          verify=matches == "verified")
        return read_database(database, matches)
