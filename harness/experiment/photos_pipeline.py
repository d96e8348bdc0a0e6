"""The ``photos`` pipeline of a run: one photo data set, one structure-from-motion method, scored by pose AUC.

A practitioner's question as an experiment: which method to trust on
photos like theirs. The data set is a folder of photos with its reference
poses (``photos.set``, a subfolder of ``photos.root``: see
:mod:`mpe3d.harness.userdata.photo_sets`) or a rendered set (the bundled
``shape`` photographed along :func:`~mpe3d.harness.scene.rendering.photo_spiral`,
exact reference poses). Its SIFT features and raw matches are computed once
and shared by every method (:mod:`.features`); their tracks go to the method
``photos.solver``: mpe3d's bundle adjustment, COLMAP's incremental or global
mapper (each verifying the same raw matches itself), or an SfM plug-in
(:mod:`mpe3d.solvers.sfm.methods`), exactly as ``mpe3d reconstruct`` gives
them. The method never sees the reference.

Scores: COLMAP's relative-pose AUC at 1, 3, 5 and 10 degrees over every
ordered pair of the reference's photos (180 degrees for a pair the method did
not register together), the photos registered, the camera-centre error after
a similarity, the reprojection RMS, the points placed, and the time split:
extract and match (when they were computed: ``features_cached`` says if this
run read them) and the method's own solve. A method that registered fewer
than two photos (:class:`~mpe3d.errors.Unregistered`) has finished, with
registered 0 and (against a reference) AUC 0. Any other error fails the run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mpe3d import solvers
from mpe3d.errors import MpeError, Unregistered
from mpe3d.harness.experiment import features as feature_cache
from mpe3d.harness.experiment.config import EVERY_SET, RENDERED, RunConfig, photo_set_folder
from mpe3d.harness.experiment.result import RunResult, short_number
from mpe3d.harness.scene.metrics import score_poses
from mpe3d.harness.scene.observe import Scene
from mpe3d.harness.userdata import photos
from mpe3d.harness.userdata.references import Reference, poses_of, read_reference, unscored
from mpe3d.solvers.sfm import methods

POSE_KEYS = ("pose_auc1", "pose_auc3", "pose_auc5", "pose_auc10")


@dataclass
class PhotoData:
    """A data set as a run sees it: its features, and its reference (not shown to the method)."""

    name: str
    features: feature_cache.Features
    reference: Reference | None
    source: Path | str


@dataclass
class Solved:
    """What a method made of the tracks, in the terms every method shares."""

    poses: dict[str, tuple[np.ndarray, np.ndarray]]  # registered photos: (R, t) world -> camera
    points_placed: int
    rms_px: float
    solve_s: float
    termination: str
    seconds: dict[str, float] = field(default_factory=dict)  # COLMAP's verify_s and map_s
    warnings: list[str] = field(default_factory=list)


def _rendered(config: RunConfig) -> PhotoData:
    found, cameras = feature_cache.rendered_set(config["shape"], config["images.count"], config["images.size"],
                                                config["seed"], config["images.matching"],
                                                feature_cache.cache_root(config["photos.cache"]))
    poses = {name: (R, t) for name, R, t in zip(found.names, cameras.rotations, cameras.translations)}
    label = data_label(config)
    return PhotoData(label, found, Reference(poses=poses, source="rendered", photos=len(poses)), label)


def _folder(config: RunConfig) -> PhotoData:
    from mpe3d.harness.userdata.photo_folder import list_photos
    from mpe3d.harness.userdata.photo_sets import IMAGES, find_reference

    images = photo_set_folder(config.values) / IMAGES
    reference_path = find_reference(images.parent)  # read before the features: a bad reference fails at once
    reference = None if reference_path is None else read_reference(reference_path, list_photos(images))
    cache = feature_cache.cache_root(config["photos.cache"])
    found = feature_cache.folder_set(images, config["images.matching"], cache)
    return PhotoData(config["photos.set"], found, reference, images)


def photo_data(config: RunConfig) -> PhotoData:
    """The run's data set, its features computed or read from the cache."""
    if config["photos.set"] == EVERY_SET:
        raise MpeError(f"photos.set={EVERY_SET} names every data set under photos.root: a sweep makes one "
                       "run of each; a run takes one (photos.set=NAME)", key="photos.set")
    return _rendered(config) if config["photos.set"] == RENDERED else _folder(config)


def _read_tracks(data: PhotoData) -> list[dict]:
    """The data set's tracks, read from a copy of its cached database: COLMAP
    writes to a database it opens (its schema, its lock), and runs of the
    other methods read the same one at the same time."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory(prefix="mpe3d-photos-") as work:
        for part in data.features.database.parent.glob(data.features.database.name + "*"):  # -wal, -shm too
            shutil.copy2(part, Path(work) / part.name)
        return photos.read_database(Path(work) / data.features.database.name, "raw", source=data.source)


def _built_in(views: list[dict], method: str, rng) -> Solved:
    from mpe3d.harness.userdata.reconstruct import prepare, solve_problem

    result = solve_problem(prepare(views, solver=method, random_state=rng))
    report = result.report
    why = unscored(result)
    return Solved(poses_of(result), len(result.ids) - len(result.unplaced), float(report["reprojection_rms_px"]),
                  float(report["runtime_s"]), str(report["termination"]), dict(report.get("colmap_seconds", {})),
                  [*result.warnings, *([why] if why else [])])


def sfm_views(views: list[dict]) -> list[methods.SfmView]:
    """The views as an SfM plug-in is given them: each photo's keypoints in its
    own pixels (a photo of several cameras had them moved by its ``offset``)."""
    out = []
    for view in views:
        offset = np.asarray(view.get("offset", (0.0, 0.0)), dtype=float)
        out.append(methods.SfmView(str(view["name"]), np.asarray(view["ids"], dtype=np.int64),
                                   np.asarray(view["xy"], dtype=float) + offset,
                                   tuple(int(v) for v in view["image_size"]), view.get("focal_px"),
                                   int(view.get("camera", 0))))
    return out


def pinhole_rms(result: methods.SfmResult, views: list[methods.SfmView]) -> float:
    """The RMS reprojection error in pixels of a plug-in's points through its
    cameras, over the observations of its points in its registered photos."""
    order = np.argsort(result.point_ids)
    squared = []
    for view in views:
        pose = result.poses.get(view.name)
        if pose is None or not len(result.point_ids):
            continue
        at = np.clip(np.searchsorted(result.point_ids, view.ids, sorter=order), 0, len(order) - 1)
        placed = result.point_ids[order[at]] == view.ids
        camera = result.points[order[at[placed]]] @ pose.rotation.T + pose.translation
        pixels = pose.focal_px * camera[:, :2] / camera[:, 2:3] + np.asarray(pose.principal_point)
        squared.append(np.sum((pixels - view.xy[placed]) ** 2, axis=1))
    squared = np.concatenate(squared) if squared else np.zeros(0)
    return float(np.sqrt(squared.mean())) if len(squared) else float("nan")


def _plugin(views: list[dict], method: str, seed: int) -> Solved:
    given = sfm_views(views)
    start = time.perf_counter()
    result = methods.run_sfm(method, given, seed)
    solve_s = time.perf_counter() - start
    poses = {name: (pose.rotation, pose.translation) for name, pose in result.poses.items()}
    return Solved(poses, len(result.point_ids), pinhole_rms(result, given), solve_s, result.termination)


def solve(views: list[dict], method: str, rng) -> Solved:
    """``method`` on the tracks of ``views``; a method that registered nothing: nothing posed."""
    start = time.perf_counter()
    try:
        if method in methods.BUILT_IN:
            return _built_in(views, method, rng)
        return _plugin(views, method, int(rng.integers(2 ** 31)))
    except Unregistered as exc:  # its honest outcome, in the time it took; any other error fails the run
        return Solved({}, 0, float("nan"), time.perf_counter() - start, str(exc), warnings=[str(exc)])


def _scores(data: PhotoData, views: list[dict], solved: Solved) -> dict[str, float]:
    nan = float("nan")
    if data.reference is not None:
        found = score_poses(data.reference, solved.poses, random_state=0)
        scores = {key: float(found[key]) for key in (*POSE_KEYS, "registered", "registered_fraction",
                                                      "centre_error", "centres_scored")}
        scores["photos"] = data.reference.photos
    else:
        scores = {**dict.fromkeys(POSE_KEYS, nan), "registered": len(solved.poses),
                  "photos": len(data.features.names), "centre_error": nan, "centres_scored": 0}
        scores["registered_fraction"] = scores["registered"] / max(scores["photos"], 1)
    seconds = data.features.seconds
    scores.update({"rms_px": solved.rms_px, "points_placed": solved.points_placed,
                   "extract_s": seconds.get("extract_s", nan), "match_s": seconds.get("match_s", nan),
                   "solve_s": solved.solve_s, "runtime_s": solved.solve_s,
                   "features_cached": float(data.features.cached), "views": len(views),
                   "tracks": len({int(i) for view in views for i in view["ids"]})})
    scores.update({key: solved.seconds[key] for key in ("verify_s", "map_s") if key in solved.seconds})
    return scores


def run(config: RunConfig, streams) -> RunResult:
    """Features (computed once per data set), the method on their tracks, its poses against the reference."""
    data = photo_data(config)
    views = _read_tracks(data)
    solved = solve(views, config["photos.solver"], streams["solver"])
    scores = _scores(data, views, solved)
    recon = solvers.Reconstruction(points=np.zeros((0, 3)), projections=np.zeros((0, 2, 3)), stress=float("nan"),
                                   stress_history=np.zeros(0), iterations=0, termination=solved.termination,
                                   runtime_s=solved.solve_s)
    # no ground-truth cloud to align a cloud to: the poses are what is scored
    scene = Scene(mesh=None, points=np.zeros((0, 3)), rotations=np.tile(np.eye(3), (len(views), 1, 1)),
                  visible=np.zeros((len(views), 0), dtype=bool))
    notes = [*data.features.notes, *(views[0].get("notes", []) if views else []),
             *(data.reference.notes if data.reference else ()), *solved.warnings]
    facts = {"warnings": notes, "dataset": data.name}
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=np.zeros((0, 3)), facts=facts)


def data_label(config: Any) -> str:
    """How a photos run's data set is named in tables: the folder, or the rendered set."""
    if config["photos.set"] == RENDERED:
        return f"{config['shape']}, {config['images.count']} photos"
    return str(config["photos.set"])


def title(result: RunResult) -> str:
    auc = result.metrics.get("pose_auc3")
    shown = f"  AUC@3 {auc:.3g}" if auc is not None and np.isfinite(auc) else ""
    return f"{data_label(result.config)}  {result.config['photos.solver']}{shown}"


def describe(summary: dict[str, Any]) -> list[str]:
    from mpe3d.harness.experiment.config import flatten

    config = flatten(summary["config"])
    lines = [f"photos {data_label(config)}: {summary['views']} photos with tracks, {summary['tracks']} tracks; "
             f"{config['photos.solver']} registered {summary['registered']:g} of {summary['photos']:g}, "
             f"placed {summary['points_placed']:g} points, reprojection RMS {short_number(summary['rms_px'])} px"]
    if np.isfinite(summary["pose_auc3"]):
        lines.append("pose AUC@1/3/5/10 " + "/".join(f"{summary[k]:.1f}" for k in POSE_KEYS)
                     + f"  centre error {short_number(summary['centre_error'])} %")
    cached = " (read from the cache)" if summary["features_cached"] else ""
    lines.append(f"{summary['termination']}; extract {summary['extract_s']:.2f} s, match {summary['match_s']:.2f} s"
                 f"{cached}, solve {summary['solve_s']:.3f} s, total {summary['wall_s']:.3f} s")
    return lines


def method_name(config) -> str:
    """How a photos run is named in tables: its structure-from-motion method."""
    return str(config["photos.solver"])
