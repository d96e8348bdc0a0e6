"""COLMAP on photos through pycolmap: structure from motion, and its feature tracks.

* :func:`run_sfm`: SIFT extraction, matching (exhaustive for few photos,
  sequential along the camera path for many) and incremental mapping, on
  one thread with a fixed seed so that a run repeats;
* :func:`database_tracks`: COLMAP's feature tracks, the connected
  components of its geometrically verified matches, before any
  triangulation (what the paper fed to 3DMPE).

Reading and writing model folders is :mod:`mpe3d.harness.userdata.colmap_model`'s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpe3d.harness.userdata.colmap_model import require_pycolmap

EXHAUSTIVE_UP_TO = 50  # photos; beyond, matching pairs each photo with its path neighbours


SEQUENTIAL_OVERLAP = 10  # neighbours on each side of a photo along the path


def colmap_version() -> str:
    pycolmap = require_pycolmap()
    return f"pycolmap {pycolmap.__version__} ({pycolmap.COLMAP_version})"


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
