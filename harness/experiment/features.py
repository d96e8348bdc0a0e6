"""A photo data set's features and matches, computed once and shared by every method.

The ``photos`` pipeline compares structure-from-motion methods on identical
matches, so SIFT and the matcher run once per data set, not once per run:
their database is cached under ``photos.cache`` (default
``$XDG_CACHE_HOME/mpe3d/features``) by a key made of

* what the photos are: a folder's bytes (its content digest), or a rendered
  set's inputs (the mesh's bytes, photo count, size and seed);
* how they were matched: the extraction's options;
* the code that made them: pycolmap's version and the fingerprint of every
  module the photos and the database go through (:data:`FEATURE_CODE`), so
  that features made by other code are never reused (they are made again).

Runs of one data set in parallel workers wait on a lock for the first to
finish rather than all extracting; an entry is written into a temporary
folder and renamed into place, so a reader never sees half of one. The
seconds the extraction and matching took when they were computed are kept
with the entry, and every run reports them (``features_cached`` says whether
it computed them itself).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

from mpe3d.errors import MachineError
from mpe3d.harness.files import cache_folder, no_space

# The modules that make a data set's photos and database (this one holds how they are
# asked for): a change to any makes them again.
FEATURE_CODE = ("mpe3d.harness.scene.shapes", "mpe3d.harness.scene.rendering", "mpe3d.harness.userdata.photo_folder",
                "mpe3d.solvers.sfm.colmap", "mpe3d.harness.experiment.features")
MAX_FEATURES = 8192  # SIFT features a photo, COLMAP's default and mpe3d reconstruct's
FOLDER_SEED = 0  # a folder's features do not depend on a run's seed: every seed shares them
DATABASE = "database.db"
META = "features.json"


@dataclass
class Features:
    """A data set's features and matches in a COLMAP database, and what they cost."""

    database: Path
    names: list[str]  # the photos extracted, in order
    seconds: dict[str, float]  # extract_s, match_s (render_s for a rendered set), when computed
    cached: bool  # read from the cache: this run did not compute them
    notes: list[str] = field(default_factory=list)  # photos skipped, and why


def _extract(image_dir: Path, names: list[str], matching: str, seed: int, database: Path) -> dict:
    from mpe3d.solvers.sfm import colmap

    return colmap.extract_and_match(database, image_dir, names, matching=matching, threads=1,
                                    max_features=MAX_FEATURES, verify=False, seed=seed)


def rendered_set(shape: str, count: int, size: int, seed: int, matching: str, root: Path):
    """A rendered photo set's features (the photos rendered with them, under
    the entry) and its cameras, whose poses are the set's reference."""
    from mpe3d.harness.experiment.datasets import shape_data
    from mpe3d.harness.scene import rendering, shapes

    cameras = rendering.photo_spiral(count, size, seed)

    def make(work: Path):
        start = time.perf_counter()
        names = rendering.save_images(rendering.render(shapes.load_shape(shape), cameras, seed=seed), work / "images")
        render_s = time.perf_counter() - start
        return names, {"render_s": render_s, **_extract(work / "images", names, matching, seed, work / DATABASE)}, []

    what = {"rendered": shape_data(shape), "count": count, "size": size, "seed": seed, "max_features": MAX_FEATURES,
            "matching": matching}
    return features(root, feature_key(what), make), cameras


def folder_set(images: Path, matching: str, root: Path) -> Features:
    """A folder of photos' features: every run's, whatever its seed (they do not depend on it)."""
    from mpe3d.harness.userdata.formats import content_digest
    from mpe3d.harness.userdata.photo_folder import usable_photos

    def make(work: Path):
        found = usable_photos(images, work)
        return found.names, _extract(found.image_dir, found.names, matching, FOLDER_SEED, work / DATABASE), \
            found.skipped

    what = {"photos": content_digest(images), "max_features": MAX_FEATURES, "matching": matching}
    return features(root, feature_key(what), make)


def cache_root(folder: str | None) -> Path:
    """``photos.cache``, or the user's cache folder."""
    return Path(folder).expanduser() if folder else cache_folder() / "features"


def feature_key(what: dict) -> str:
    """The cache key of the features of ``what`` (the photos and the options),
    made by this code and this pycolmap."""
    from mpe3d.harness.tracking.identity import module_file, source_fingerprint
    from mpe3d.solvers.sfm import colmap

    code = {name: source_fingerprint(module_file(name).read_text()) for name in FEATURE_CODE}
    text = json.dumps({"what": what, "colmap_version": colmap.version(), "code": code}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    with _cache_errors(path.parent):
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a")
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # another worker extracting the same set: wait for it
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _read(entry: Path) -> Features | None:
    try:
        meta = json.loads((entry / META).read_text())
    except (OSError, ValueError):
        return None  # no entry, or one this code cannot read: made again
    if not (entry / DATABASE).is_file():
        return None
    return Features(entry / DATABASE, list(meta["names"]), dict(meta["seconds"]), True, list(meta["notes"]))


def features(root: Path, key: str, make: Callable[[Path], tuple[list[str], dict, list[str]]]) -> Features:
    """The features of ``key`` under ``root``: read, or made by ``make(folder)``
    (which writes ``folder/database.db`` and returns the photo names, the
    seconds of each step and notes) and kept."""
    entry, work = root / key, root / f".{key}.{os.getpid()}.tmp"
    with _locked(root / f"{key}.lock"):
        found = _read(entry)
        if found is not None:
            return found
        with _cache_errors(root):
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir()
        try:
            names, seconds, notes = make(work)  # its own errors are its own: the photos', COLMAP's
            with _cache_errors(root):
                (work / META).write_text(json.dumps({"names": names, "seconds": seconds, "notes": notes}))
                shutil.rmtree(entry, ignore_errors=True)  # an entry this code could not read
                os.replace(work, entry)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return Features(entry / DATABASE, names, seconds, False, notes)


@contextmanager
def _cache_errors(root: Path) -> Iterator[None]:
    """The cache folder's own failures as one line (exit 3): no space, no write access."""
    try:
        yield
    except OSError as exc:
        if no_space(exc):
            raise MachineError(f"photos.cache {root}: no space left for a data set's features "
                               "(give photos.cache=DIR on a larger disk)") from None
        raise MachineError(f"photos.cache {root}: cannot write the features there: "
                           f"{exc.strerror or exc}") from None
