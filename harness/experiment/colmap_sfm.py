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

from mpe3d.harness.userdata.photos import FeatureTracks, extract_and_match, match_tracks
from mpe3d.solvers.sfm.colmap_link import require_pycolmap


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
    seconds = extract_and_match(database, image_dir, names, camera_model="SIMPLE_PINHOLE",
                                camera_params=f"{focal},{principal_point[0]},{principal_point[1]}",
                                matching=matching, threads=1, max_features=max_features)
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


def database_tracks(database: Path) -> FeatureTracks:
    """COLMAP's feature tracks: its verified matches joined (what the paper fed to 3DMPE)."""
    return match_tracks(database, "verified")


def triangulated(tracks: FeatureTracks, sfm: SfmResult) -> dict[int, int]:
    """track -> the point3D of COLMAP's model that most of its keypoints went to."""
    votes: dict[int, dict[int, int]] = {}
    for t, k, kp in zip(tracks.track, tracks.image, tracks.keypoint):
        point = sfm.image_points.get(tracks.names[k], {}).get(int(kp))
        if point is not None:
            votes.setdefault(int(t), {}).setdefault(point, 0)
            votes[int(t)][point] += 1
    return {t: max(v, key=v.get) for t, v in votes.items()}
