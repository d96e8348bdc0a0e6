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

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image as PILImage

from mpe3d.harness.userdata.photos import FeatureTracks, match_tracks
from mpe3d.solvers.sfm import colmap
from mpe3d.solvers.sfm.colmap_mapper import majority_points


def colmap_version() -> str:
    return colmap.version()


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
    image_points: dict[str, np.ndarray] = field(default_factory=dict)  # name -> point3D id per keypoint, -1 none
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def centres(self) -> dict[str, np.ndarray]:
        return {name: -R.T @ t for name, (R, t) in self.registered.items()}


def run_sfm(image_dir: Path, names: list[str], workdir: Path, *, focal: float,
            principal_point, matching: str = "auto", seed: int = 0,
            max_features: int = 8192) -> SfmResult:
    """COLMAP on ``names`` in ``image_dir``: one shared SIMPLE_PINHOLE camera
    started at ``focal`` (refined by the mapper, as for photos whose EXIF
    gives the focal length), SIFT, matching, incremental mapping, on one
    thread with the run's seed (so that a run repeats)."""
    database = workdir / "database.db"
    database.unlink(missing_ok=True)
    with PILImage.open(image_dir / names[0]) as first:
        width, height = first.size
    camera = colmap.simple_camera("SIMPLE_PINHOLE", width, height, focal, principal_point)
    # COLMAP aborts the process when the disk fills under its writer threads
    colmap.check_space(workdir, colmap.scratch_bytes(len(names), max_features,
                                                     colmap.matched_pairs(len(names), matching), True), given=False)
    seconds = colmap.extract_and_match(database, image_dir, names, camera=camera, matching=matching,
                                       threads=1, max_features=max_features, seed=seed)
    model = colmap.incremental_mapping(database, image_dir, workdir / "sparse", seed=seed)
    if model is None:  # the mapper made no model at all
        return SfmResult(database, names, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), {}, 0, None, None,
                         {}, seconds)
    seconds.update(model.seconds)
    registered = {name: (image.rotation, image.translation) for name, image in model.images.items()}
    camera = next(iter(model.cameras.values()))
    return SfmResult(database, names, model.points, model.point_ids, registered, model.models,
                     camera.focal, model.reprojection_px,
                     {name: image.point3d for name, image in model.images.items()}, seconds)


def database_tracks(database: Path) -> FeatureTracks:
    """COLMAP's feature tracks: its verified matches joined (what the paper fed to 3DMPE)."""
    return match_tracks(database, "verified")


def triangulated(tracks: FeatureTracks, sfm: SfmResult) -> dict[int, int]:
    """track -> the point3D of COLMAP's model that most of its keypoints went to."""
    point3d = np.full(len(tracks.track), -1, dtype=np.int64)
    for k, name in enumerate(tracks.names):
        ids = sfm.image_points.get(name)
        rows = np.flatnonzero(tracks.image == k)
        if ids is not None and len(rows):
            point3d[rows] = ids[tracks.keypoint[rows]]
    chosen = majority_points(tracks.track, point3d, tracks.n_tracks)
    return {int(t): int(chosen[t]) for t in np.flatnonzero(chosen >= 0)}
