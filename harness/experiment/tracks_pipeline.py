"""The ``tracks`` pipeline of a run: a real keypoint data set, perturbed, solved and scored.

A practitioner's question as an experiment: which camera model, loss or
solver to trust on *their* keypoints, and how each degrades with noise,
missing observations and wrong matches. The data set (``tracks.path``, any
input :func:`mpe3d.harness.userdata.reconstruct.reconstruct` reads) is
perturbed by seeded draws from the run's ``noise`` stream, then solved
exactly as ``mpe3d reconstruct`` solves it. The solver sees the perturbed
observations only; the clean ones, the reference points (``tracks.truth``)
and cameras (``tracks.cameras``) are used after it, to score.

Scores: the reprojection RMS in pixels over the kept observations, over all
of them, and on the clean observations (each untouched observation against
its coordinates before noise, wherever the solver put its point); the 3D
error after the robust similarity onto the reference points, in percent of
their bounding-box diagonal (RMS, median, and median over the points that
no wrong match touched); the camera-centre error after the same similarity,
over the views the method registered, each against the reference camera of
its view in the data set (``centres_scored`` of them).

A structure-from-motion method that registered fewer than two views
(:class:`~mpe3d.errors.Unregistered`) has finished: its run has no cloud,
``registered_views`` 0 and NaN scores. Any other error, the input's refusal
before a method is called included, fails the run, whichever method was asked.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mpe3d import solvers
from mpe3d.errors import MpeError, Unregistered
from mpe3d.harness.experiment.config import RunConfig, flatten, track_file
from mpe3d.harness.experiment.result import RunResult, short_number
from mpe3d.harness.scene import metrics
from mpe3d.harness.scene.observe import Scene
from mpe3d.harness.userdata import vgg
from mpe3d.harness.userdata.formats import content_digest, read_points, read_projections, read_views
from mpe3d.harness.userdata.reconstruct import prepare, solve_problem
from mpe3d.harness.userdata.results import Result
from mpe3d.solvers.degenerate import MIN_VIEW_POINTS
from mpe3d.solvers.linalg import elongation


@dataclass(frozen=True)
class Perturbed:
    """The observations the solver is given, and what they were before."""

    views: list[dict]
    clean: np.ndarray  # (M, 2) each kept observation before noise and wrong matches, views' order
    wrong: np.ndarray  # (M,) bool: replaced by another track's observation in its view
    removed: int  # observations removed (tracks.drop_fraction)
    notes: tuple[str, ...] = ()


def read_data(config: RunConfig) -> list[dict]:
    """The data set's views (the first ``tracks.views`` of them), 2D keypoints required."""
    path = track_file(config.values, "tracks.path")
    views = read_views(path)
    if any("xy" not in view for view in views):
        raise MpeError(f"{path}: pipeline=tracks perturbs 2D keypoints; this input holds distance "
                       "matrices (reconstruct it with `mpe3d reconstruct`)")
    count = config["tracks.views"]
    if count is not None:
        if count > len(views):
            raise MpeError(f"tracks.views: {count} views asked, {path} has {len(views)}")
        views = views[:count]
    # a view is known by its name from here on (a nameless one by its place in the data set)
    return [{**view, "name": str(view.get("name", k))} for k, view in enumerate(views)]


def _rows_by_view(views: list[dict]) -> np.ndarray:
    return np.concatenate([np.full(len(view["ids"]), k) for k, view in enumerate(views)])


def _keep(view: dict, rows: np.ndarray) -> dict:
    """``view`` with only its observations ``rows`` (and their start points)."""
    return {**view, **{key: np.asarray(view[key])[rows] for key in ("ids", "xy", "start_points")
                       if key in view}}


def perturb(views: list[dict], drop: float, wrong: float, noise_px: float,
            rng: np.random.Generator) -> Perturbed:
    """Remove a share ``drop`` of the observations, replace a share ``wrong`` of
    the rest by another track's observation in the same view, and add Gaussian
    noise of ``noise_px`` pixels to every one. Each perturbation draws from its
    own child of ``rng``, so changing one share leaves the others' draws alone.
    A view left with fewer than MIN_VIEW_POINTS (3) observations is removed, with a note."""
    drop_rng, wrong_rng, noise_rng = rng.spawn(3)
    owner = _rows_by_view(views)
    gone = np.zeros(len(owner), dtype=bool)
    gone[drop_rng.choice(len(owner), int(round(drop * len(owner))), replace=False)] = True
    kept_views, notes = [], []
    for k, view in enumerate(views):
        rows = np.flatnonzero(~gone[owner == k])
        if len(rows) < MIN_VIEW_POINTS:
            notes.append(f"view '{view.get('name', k)}' kept {len(rows)} observation(s) after "
                         f"tracks.drop_fraction={drop:g}: left out")
            continue
        kept_views.append(_keep(view, rows))
    if len(kept_views) < 2:
        raise MpeError(f"tracks.drop_fraction={drop:g} leaves {len(kept_views)} view(s) with "
                       f"{MIN_VIEW_POINTS} observations or more; reconstruction needs 2")
    clean = np.concatenate([np.asarray(v["xy"], dtype=float) for v in kept_views])
    xy = clean.copy()
    owner = _rows_by_view(kept_views)
    changed = np.zeros(len(xy), dtype=bool)
    changed[wrong_rng.choice(len(xy), int(round(wrong * len(xy))), replace=False)] = True
    starts = np.concatenate([[0], np.cumsum([len(v["ids"]) for v in kept_views])])
    for row in np.flatnonzero(changed):
        k = owner[row]
        other = wrong_rng.integers(starts[k], starts[k + 1] - 1)  # any other row of the view
        xy[row] = clean[other + (other >= row)]
    if noise_px > 0:
        xy += noise_rng.normal(0.0, noise_px, xy.shape)
    out = [{**view, "xy": xy[starts[k]:starts[k + 1]]} for k, view in enumerate(kept_views)]
    return Perturbed(out, clean, changed, int(gone.sum()), tuple(notes))


def _problem(config: RunConfig, views: list[dict], rng):
    objective = config["tracks.objective"]
    return prepare(views, solver=config.solver if objective == "stress" else config["tracks.solver"],
                   loss=config["tracks.loss"], random_state=rng, objective=objective,
                   camera=config["tracks.camera"] if objective == "reprojection" else "auto",
                   outlier_threshold=config["tracks.outlier_threshold"],
                   start=config["tracks.start"] if objective == "reprojection" else "own")


def affine_residuals(points: np.ndarray, projections: np.ndarray, obs) -> np.ndarray:
    """Residuals (pixels) of each view's keypoints against the stress solution
    seen through its estimated projection rows, with the view's best scale and
    shift (a scaled orthographic camera): what the stress leaves undetermined."""
    out = []
    for P, view in zip(projections, obs.views):
        seen = points[view.ids] @ P.T
        a, b = seen - seen.mean(0), view.coordinates - view.coordinates.mean(0)
        scale = float(np.sum(a * b) / max(np.sum(a * a), 1e-300))
        out.append(scale * a - b)
    return np.concatenate(out)


def _reprojection_scores(result: Result, perturbed: Perturbed, problem) -> dict[str, float]:
    residuals, counted = result.residuals, result.counted
    if residuals is None:  # the stress: its views' scaled orthographic fit
        residuals = affine_residuals(result.points, result.projections, problem.observations)
        counted = np.ones(len(residuals), dtype=bool)
    placed = ~np.isin(problem.ids[np.concatenate([v.ids for v in problem.observations.views])],
                      result.unplaced)
    observed = np.concatenate([v.coordinates for v in problem.observations.views])
    on_clean = residuals + observed - perturbed.clean  # projection minus the clean keypoint
    rows = ~perturbed.wrong & placed

    def rms(r):
        return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))) if len(r) else float("nan")

    dropped = ~counted & placed
    posed = np.all(np.isfinite(residuals), axis=1)  # a view the mapper left out has no residual
    rows &= posed
    return {"rms_px": rms(residuals[counted]), "rms_px_all": rms(residuals[posed]),
            "rms_px_clean": rms(on_clean[rows]), "caught": int(np.sum(dropped & perturbed.wrong)),
            "clean_dropped": int(np.sum(dropped & ~perturbed.wrong))}


def _centres(result: Result) -> dict[str, np.ndarray] | None:
    """The centres of the cameras the method registered, by view name; None
    for affine cameras, which have no centre."""
    cameras = [c for c in result.cameras if c.registered]
    if not cameras or any(c.focal_px is None for c in cameras):
        return None
    return {c.view: -c.rotation.T @ c.translation for c in cameras}


def _reference_centres(P: np.ndarray) -> np.ndarray:
    """Each 3x4 camera's centre: the null vector of P."""
    return np.stack([(lambda v: v[:3] / v[3])(np.linalg.svd(m)[2][-1]) for m in P])


def _truth_scores(result: Result, perturbed: Perturbed, problem, truth, reference, rng):
    """3D and camera-centre errors after the robust similarity onto the reference
    (a mirror allowed: the views alone cannot tell a shape from its mirror)."""
    ids, points = truth
    index = {str(i): r for r, i in enumerate(ids)}
    placed = ~np.isin(result.ids, result.unplaced)
    rows = [(k, index[str(i)]) for k, i in enumerate(result.ids) if placed[k] and str(i) in index]
    if len(rows) < 4:
        return {}, np.zeros((0, 3)), np.zeros((0, 3))
    ours, theirs = (np.array(c) for c in zip(*rows))
    fit = metrics.robust_similarity(result.points[ours], points[theirs], rng, mirror=True)
    s, Q, t = fit
    aligned = s * result.points[ours] @ Q.T + t
    scale = float(np.linalg.norm(np.ptp(points[theirs], axis=0)))
    apart = 100.0 * np.linalg.norm(aligned - points[theirs], axis=1) / scale
    point_of_row = np.concatenate([v.ids for v in problem.observations.views])
    touched = np.zeros(len(result.ids), dtype=bool)
    touched[point_of_row[perturbed.wrong]] = True
    untouched = ~touched[ours]
    out = {"error_3d_pct": float(np.sqrt(np.mean(apart ** 2))),
           "error_3d_median_pct": float(np.median(apart)),
           "error_3d_clean_median_pct": float(np.median(apart[untouched])) if untouched.any()
           else float("nan"), "points_scored": len(ours)}
    centres = _centres(result)
    # each registered view against the reference camera of the same name
    names = [name for name in (centres or {}) if reference is not None and name in reference]
    if names:
        true = _reference_centres(np.stack([reference[name] for name in names]))
        moved = s * np.stack([centres[name] for name in names]) @ Q.T + t
        out["centre_error_pct"] = float(np.median(100.0 * np.linalg.norm(moved - true, axis=1) / scale))
        out["centres_scored"] = len(names)
    return out, aligned, points[theirs]


def _reference(config: RunConfig, views: list[dict]):
    """The reference points (ids, (N, 3)) and cameras ({view name: 3x4}), where
    the data set has them: ``tracks.truth`` and ``tracks.cameras`` (one matrix
    per view of the data set, in its order), else a VGG set's own files."""
    truth_path, cameras_path = (track_file(config.values, k) for k in ("tracks.truth", "tracks.cameras"))
    truth = read_points(truth_path) if truth_path is not None else None
    reference = None
    if cameras_path is not None:
        matrices = read_projections(cameras_path)
        if matrices.shape[1:] != (3, 4):
            raise MpeError(f"{cameras_path}: tracks.cameras takes 3x4 pinhole matrices")
        cut = config["tracks.views"] is not None  # the first tracks.views of the data set's views
        if len(matrices) < len(views) or (len(matrices) != len(views) and not cut):
            raise MpeError(f"{cameras_path}: {len(matrices)} cameras for the {len(views)} views of the data set")
        reference = {view["name"]: P for view, P in zip(views, matrices)}
    if reference is not None and len({view["name"] for view in views}) < len(views):
        raise MpeError(f"{track_file(config.values, 'tracks.path')}: two views share a name; the reference "
                       "cameras are matched to the views by name")
    data = track_file(config.values, "tracks.path")
    if (truth is None or reference is None) and data.is_file() and vgg.sniff(data):
        found_truth, found_cameras = vgg.read_reference(data)  # its .p3d and .P files, if any
        truth = truth if truth is not None else found_truth
        reference = reference if reference is not None else found_cameras
    return truth, reference


def _unregistered(config: RunConfig, perturbed: Perturbed, problem, error: Unregistered) -> RunResult:
    """The run of a method that registered no two views (its honest outcome, a
    finished run): no cloud, every score but the counts undefined (NaN), the
    reason among its warnings."""
    obs = problem.observations
    nan = float("nan")
    scores = {"observations": len(perturbed.clean), "removed": perturbed.removed,
              "wrong": int(perturbed.wrong.sum()), "views_kept": obs.n_views, "tracks": obs.n_points,
              "dropped": 0, "unplaced": obs.n_points, "converged": 0.0, "registered_views": 0,
              "iterations": 0, "runtime_s": nan, "rms_px": nan, "rms_px_all": nan, "rms_px_clean": nan,
              "caught": 0, "clean_dropped": 0}
    recon = solvers.Reconstruction(points=np.zeros((0, 3)), projections=np.zeros((0, 2, 3)), stress=nan,
                                   stress_history=np.zeros(0), iterations=0, termination=str(error),
                                   runtime_s=nan)
    scene = Scene(mesh=None, points=np.zeros((0, 3)), rotations=np.tile(np.eye(3), (obs.n_views, 1, 1)),
                  visible=obs.visibility().astype(bool))
    facts = {"warnings": list(perturbed.notes) + [str(error)],
             "tracks_sha256": content_digest(track_file(config.values, "tracks.path")),
             "camera_fitted": "none"}
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=np.zeros((0, 3)), facts=facts)


def run(config: RunConfig, streams) -> RunResult:
    """Read, perturb, solve, score; the solver only ever sees the perturbed keypoints."""
    views = read_data(config)
    perturbed = perturb(views, config["tracks.drop_fraction"], config["tracks.wrong_fraction"],
                        config["tracks.noise_px"], streams["noise"])
    problem = _problem(config, perturbed.views, streams["solver"])
    try:
        result = solve_problem(problem)
    except Unregistered as exc:  # a method that registers nothing is a result; any other error fails the run
        return _unregistered(config, perturbed, problem, exc)
    report = result.report
    scores: dict[str, float] = {
        "observations": len(perturbed.clean), "removed": perturbed.removed,
        "wrong": int(perturbed.wrong.sum()), "views_kept": problem.observations.n_views,
        "tracks": problem.observations.n_points, "dropped": len(result.dropped),
        "unplaced": len(result.unplaced), "converged": float(report.get("converged", True)),
        "registered_views": sum(c.registered for c in result.cameras) if result.cameras
        else problem.observations.n_views,
        "iterations": int(report["iterations"]), "runtime_s": float(report["runtime_s"])}
    scores.update(_reprojection_scores(result, perturbed, problem))
    placed = ~np.isin(result.ids, result.unplaced)
    if placed.sum() >= 3:  # a run-away solve leaves a cloud far longer than wide
        scores["elongation"] = elongation(result.points[placed])
    truth, reference = _reference(config, views)
    aligned, matched = result.points, np.zeros((0, 3))
    if truth is not None:
        found, aligned, matched = _truth_scores(result, perturbed, problem, truth, reference,
                                                streams["metrics"])
        scores.update(found)
    recon = solvers.Reconstruction(points=result.points, projections=np.asarray(result.projections),
                                   stress=float(report.get("stress", np.nan)),
                                   stress_history=np.zeros(0), iterations=scores["iterations"],
                                   termination=str(report["termination"]),
                                   runtime_s=scores["runtime_s"])
    visible = problem.observations.visibility().astype(bool)
    rotations = np.tile(np.eye(3), (problem.observations.n_views, 1, 1))
    scene = Scene(mesh=None, points=matched, rotations=rotations, visible=visible)
    facts = {"warnings": list(perturbed.notes) + list(result.warnings),
             "tracks_sha256": content_digest(track_file(config.values, "tracks.path")),
             "camera_fitted": str(report.get("camera", "stress"))}
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=aligned, facts=facts)


def method_name(config) -> str:
    """How a tracks run is named in tables: bundle adjustment or one of COLMAP's mappers
    (``tracks.solver``: bundle, colmap, colmap_global) with its camera, or the stress solver."""
    if config["tracks.objective"] == "stress":
        return f"stress ({config['solver.name']})"
    return f"{config['tracks.solver']} ({config['tracks.camera']})"


def title(result: RunResult) -> str:
    error = result.metrics.get("error_3d_median_pct")
    shown = f"  3D error {error:.3g} %" if error is not None else ""
    return f"{result.config['tracks.path']}  {method_name(result.config)}{shown}"


def describe(summary: dict[str, Any]) -> list[str]:
    tracks = summary["config"]["tracks"]
    lines = [f"tracks {tracks['path']}: {summary['views_kept']} views, {summary['tracks']} tracks, "
             f"{summary['observations']} observations ({summary['removed']} removed, "
             f"{summary['wrong']} wrong, noise {tracks['noise_px']} px), seed {summary['config']['seed']}",
             f"{method_name(flatten(summary['config']))}: reprojection RMS {short_number(summary['rms_px'])} px "
             f"kept, {short_number(summary['rms_px_all'])} px all, {short_number(summary['rms_px_clean'])} "
             f"px on the clean observations; {summary['dropped']} dropped ({summary['caught']} of "
             f"them wrong), {summary['unplaced']} unplaced"]
    if "error_3d_median_pct" in summary:
        lines.append("  ".join(f"{k}={short_number(summary[k])}" for k in
                               ("error_3d_pct", "error_3d_median_pct", "error_3d_clean_median_pct",
                                "centre_error_pct", "centres_scored") if k in summary))
    lines.append(f"{summary['termination']}; solve {summary['runtime_s']:.3f} s, "
                 f"total {summary['wall_s']:.3f} s")
    return lines

