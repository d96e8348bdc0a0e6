"""A user's photos and COLMAP databases in: SIFT features, matches and their tracks.

* :func:`read_photos`: a folder of photos (every image COLMAP reads; other
  files ignored, a damaged image skipped with a warning naming it) through
  COLMAP's SIFT and matcher, into a database in a scratch folder (``scratch``,
  its free space checked first), then read as :func:`read_database` reads one;
* :func:`match_tracks`: a database's matches joined into tracks (union-find
  over the matched keypoints), the matcher's raw matches or those its
  geometric verification kept; a track that holds two keypoints of one
  photo is inconsistent and dropped;
* :func:`read_database`: its tracks as keypoint views for
  :func:`mpe3d.harness.userdata.reconstruct.reconstruct`, each photo's
  keypoints taken through its own camera (:func:`camera_views`).

Every COLMAP call goes through :mod:`mpe3d.solvers.sfm.colmap`. ``matches``
defaults to ``raw`` for every input (glossary, docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.harness.userdata.photo_folder import list_photos, usable_photos
from mpe3d.options import DEFAULT_MATCHES, MATCHES, Interval
from mpe3d.solvers.degenerate import MIN_VIEW_POINTS, SHARED_VARIABLE, shared_points, view_groups
from mpe3d.solvers.sfm import colmap

# An EXIF focal length is trusted between these multiples of the larger image
# side (fields of view of about 14 to 118 degrees); beyond, it is a camera's
# lie or a resized photo's stale tag (3,767 px for a 640-px image).
PLAUSIBLE_FOCAL = Interval(float, 0.3, 4.0)
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

    def views(self, min_points: int = MIN_VIEW_POINTS) -> list[dict]:
        """One keypoint view per photo (tracks as ids), photos with fewer than
        ``min_points`` tracks left out."""
        out = []
        for k, name in enumerate(self.names):
            rows = np.flatnonzero(self.image == k)
            if len(rows) >= min_points:
                out.append({"name": name, "ids": self.track[rows], "xy": self.xy[rows]})
        return out


def looks_like_database(path: Path) -> bool:
    """A COLMAP database is an SQLite file (any name; COLMAP's is ``database.db``)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(SQLITE_HEADER)) == SQLITE_HEADER
    except OSError:
        return False


def match_tracks(database: Path, matches: str = DEFAULT_MATCHES) -> FeatureTracks:
    """Union-find over every match of ``database`` (``matches``: the matcher's
    raw ones, or the inliers of its geometric verification)."""
    MATCHES.check("matches", matches)
    return tracks_of(colmap.read_database(database, matches))


def tracks_of(db: colmap.Database) -> FeatureTracks:
    """A database's matches joined into tracks."""
    keypoints = db.keypoints
    offsets = np.concatenate([[0], np.cumsum([len(kp) for kp in keypoints])]).astype(np.int64)
    edges = [np.column_stack([offsets[a] + pair[:, 0], offsets[b] + pair[:, 1]])
             for (a, b), pair in zip(db.pairs, db.matches) if len(pair)]
    if not edges:
        empty = np.zeros(0, dtype=np.int64)
        return FeatureTracks(db.names, empty, empty, empty, np.zeros((0, 2)), 0)
    return _union(db.names, keypoints, offsets, np.concatenate(edges))


def _union(names, keypoints, offsets, edges) -> FeatureTracks:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    total = int(offsets[-1])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    node = np.unique(edges)  # keypoints in some match
    image = (np.searchsorted(offsets, node, side="right") - 1).astype(np.int64)
    label = label[node]
    per_track = np.bincount(label)
    distinct = np.zeros_like(per_track)
    labels, counts = photos_per_label(label, image, len(names))
    distinct[labels] = counts
    good = per_track == distinct  # no photo twice
    keep = good[label] & (per_track[label] >= 2)
    _, track = np.unique(label[keep], return_inverse=True)
    node, image = node[keep], image[keep]
    xy = np.concatenate(keypoints)[node].astype(float)
    return FeatureTracks(names, image, track.astype(np.int64), node - offsets[image], xy,
                         int(np.count_nonzero(~good & (per_track >= 2))))


def photos_per_label(label: np.ndarray, image: np.ndarray, n_images: int) -> tuple[np.ndarray, np.ndarray]:
    """(labels, counts): how many distinct photos the keypoints of each label
    are in. In int64: csgraph's labels are int32, and a label times the photo
    count passes 2**31 at 512 photos of 8,192 keypoints."""
    keys = np.unique(np.asarray(label, dtype=np.int64) * n_images + np.asarray(image, dtype=np.int64))
    return np.unique(keys // n_images, return_counts=True)


def tied_views(views: list[dict]) -> list[dict]:
    """The largest group of ``views`` that shared tracks tie together (the
    rule of :func:`mpe3d.solvers.degenerate.check_geometry`), as COLMAP keeps
    its largest model: photos that no track links to the rest fix nothing."""
    n = 1 + max(int(v["ids"].max()) for v in views)
    view = np.concatenate([np.full(len(v["ids"]), k, dtype=np.int64) for k, v in enumerate(views)])
    count, labels = view_groups(shared_points(view, np.concatenate([v["ids"] for v in views]), len(views), n),
                                SHARED_VARIABLE)
    largest = np.argmax(np.bincount(labels))
    return [v for v, label in zip(views, labels) if label == largest]


def _trusted_focal(camera: colmap.Camera) -> float | None:
    """The camera's focal length when it is known (EXIF, a calibration) and plausible."""
    ratio = camera.focal / max(camera.width, camera.height)
    return camera.focal if camera.prior_focal and ratio in PLAUSIBLE_FOCAL else None


def _camera_of(db: colmap.Database, row: int, source) -> colmap.Camera:
    """Photo ``row``'s camera, checked; one line naming the photo when mpe3d cannot model it."""
    camera_id = int(db.camera_of[row])
    where = f"{source}: photo {db.names[row]}"
    if camera_id not in db.cameras:
        raise MpeError(f"{where}: its camera {camera_id} is not in the database")
    return db.cameras[camera_id].check(where)


def camera_views(views: list[dict], db: colmap.Database, source) -> tuple[list[dict], list[str]]:
    """Each view with its photo's camera: keypoints as a pinhole of square
    pixels and no lens sees them (each camera's own model and parameters
    taken out, as COLMAP wrote them), its principal point, image size and,
    when known and plausible, focal length; with notes for the report.

    One camera for all photos: its principal point, and its focal length.
    Several: every photo's keypoints at its own camera's focal length, moved
    round the first camera's principal point (bundle adjustment has one),
    the view marked with its ``camera`` (a focal length fitted per camera,
    never fixed from EXIF: COLMAP's EXIF focal length of a cropped photo is
    off by the crop) and its ``offset``, its own principal point less that
    one, which the reported camera gets back."""
    row = {name: k for k, name in enumerate(db.names)}
    # COLMAP's extractor writes a camera per photo by default: photos whose
    # cameras are alike (model, size, parameters) share one
    alike: dict[tuple, colmap.Camera] = {}
    of = []
    for view in views:
        camera = _camera_of(db, row[view["name"]], source)
        of.append(alike.setdefault((camera.model, camera.width, camera.height, camera.params,
                                    camera.prior_focal), camera))
    first = of[0]
    centre = first.principal_point
    several = len(alike) > 1
    out = []
    for view, camera in zip(views, of):
        own = camera.principal_point
        plain = camera.is_pinhole and np.array_equal(own, centre)
        try:
            xy = view["xy"] if plain else camera.to_pinhole(view["xy"], camera.focal, centre)
        except MpeError as exc:
            raise MpeError(f"{source}: photo {view['name']}: {exc}") from None
        facts = {"xy": xy, "principal_point": tuple(float(v) for v in centre),
                 "image_size": (camera.width, camera.height)}
        if several:
            facts["camera"], facts["offset"] = camera.camera_id, tuple(float(v) for v in own - centre)
        elif _trusted_focal(first) is not None:
            facts["focal_px"] = _trusted_focal(first)
        out.append({**view, **facts})
    notes = [f"{len(alike)} cameras: each photo's keypoints taken through its own camera, a focal "
             "length fitted per camera"] if several else []
    return out, notes


def read_database(path: str | Path, matches: str = DEFAULT_MATCHES, *, source=None) -> list[dict]:
    """A COLMAP database's tracks as keypoint views (see the module's docstring);
    its messages name ``source`` (the photo folder whose database it is), else it."""
    path = Path(path)
    MATCHES.check("matches", matches)
    db = colmap.read_database(path, matches)
    path = source if source is not None else path
    tracks = tracks_of(db)
    if not tracks.names:
        raise MpeError(f"{path}: the database holds no images")
    if not len(tracks.track):
        kind = "verified matches (run its geometric verification, or give --matches raw)" \
            if matches == "verified" else "matches (run a matcher on it: colmap exhaustive_matcher)"
        raise MpeError(f"{path}: the database holds no {kind}")
    views = tracks.views()
    if len(views) < 2:
        raise MpeError(f"{path}: {len(views)} of {len(tracks.names)} photos share {MIN_VIEW_POINTS} or "
                       "more tracks with the others; reconstruction needs 2")
    tied = tied_views(views)
    notes = [] if len(tied) == len(views) else [
        f"{len(views) - len(tied)} photo(s) share too few tracks with the largest group of "
        f"{len(tied)}: left out ({', '.join(v['name'] for v in views if all(v is not t for t in tied))[:200]})"]
    tied, camera_notes = camera_views(tied, db, path)
    return [{**view, "notes": notes + camera_notes, "matches": matches} for view in tied]


def read_photos(folder: str | Path, matches: str = DEFAULT_MATCHES, *, threads: int | None = None,
                max_features: int = 8192, seed: int = 0, scratch: str | Path | None = None) -> list[dict]:
    """A folder of photos as keypoint views: SIFT features, matches and tracks
    by COLMAP, a camera per photo as COLMAP's extractor writes them (alike ones
    then shared: :func:`camera_views`), in a database under ``scratch`` (None:
    the system's temporary folder); ``seed`` for the verification's RANSAC.
    Which files are photos, and what is skipped: :mod:`.photo_folder`."""
    from mpe3d.solvers import threads as solver_threads

    folder = Path(folder)
    MATCHES.check("matches", matches)
    count = len(list_photos(folder))
    verify = matches == "verified"  # raw matches need no geometric verification
    need = colmap.scratch_bytes(count, max_features, colmap.matched_pairs(count), verify)
    with colmap.scratch(scratch, need, prefix="mpe3d-photos-") as work:
        found = usable_photos(folder, work)
        if found.converted:  # the copies took their share: the database still needs its own
            colmap.check_space(work.parent, colmap.scratch_bytes(len(found.names), max_features,
                                                                colmap.matched_pairs(len(found.names)), verify),
                               given=scratch is not None)
        database = work / "database.db"
        colmap.extract_and_match(database, found.image_dir, found.names,
                                 threads=threads or solver_threads.count(), max_features=max_features,
                                 verify=verify, seed=seed)
        views = read_database(database, matches, source=folder)
    return [{**view, "notes": found.skipped + view["notes"]} for view in views]
