"""One run end to end: config -> scene -> observations -> solver -> metrics."""

from __future__ import annotations

import os
import socket
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from mpe3d import solvers
from mpe3d.solvers.degenerate import collect_notes

from . import metrics as metrics_mod
from .config import RunConfig
from ..errors import MpeError
from .identity import code_identity
from .limits import check_run_memory
from .observe import Scene, build_scene, observe, seed_streams

METRIC_KEYS = ("cd", "cd_mean", "emd", "emd_mean", "roa", "stress", "iterations", "runtime_s")
# BLAS sums in another order with another thread count, which moves results by
# an ulp or more; one thread everywhere (CLI, sweep parent, loky and dask
# workers) makes every run bit-identical wherever it runs. Sweeps get their
# parallelism from running several runs at once.
BLAS_THREADS = 1


@dataclass
class RunResult:
    """What a run produced: its config, metrics and the clouds behind them."""

    config: RunConfig
    metrics: dict[str, float]
    scene: Scene
    reconstruction: solvers.Reconstruction
    aligned: np.ndarray
    facts: dict[str, Any]
    wall_s: float

    def summary(self) -> dict[str, Any]:
        """The JSON contract of ``mpe3d run --json``."""
        out: dict[str, Any] = {"config": self.config.nested(), "config_hash": self.config.hash()}
        out.update({k: self.metrics[k] for k in METRIC_KEYS if k in self.metrics})
        out.update({k: v for k, v in self.metrics.items() if k not in METRIC_KEYS})
        out["visible_per_view"] = self.scene.visible_per_view
        out["warnings"] = self.facts.get("warnings", [])
        out["termination"] = self.reconstruction.termination
        out["wall_s"] = self.wall_s
        out["code"] = code_identity()
        return out


def run(config: RunConfig) -> RunResult:
    """Run ``config``; the solver only ever sees the observations."""
    check_run_memory(config)  # before sampling: refuse what cannot fit, in one line
    with threadpool_limits(limits=BLAS_THREADS):
        return _run(config)


def _run(config: RunConfig) -> RunResult:
    start = time.perf_counter()
    streams = seed_streams(config["seed"])
    if config["pipeline"] == "colmap":
        from . import pipeline_colmap

        scene, recon, aligned, scores, facts = pipeline_colmap.run(config, streams)
        return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                         aligned=aligned, facts=facts, wall_s=time.perf_counter() - start)
    scene = build_scene(config, streams)
    observations, facts = observe(scene, config, streams)
    with collect_notes() as notes:
        recon = solvers.solve(config.solver, observations, init=config["init"],
                              random_state=streams["solver"], **config.solver_options)
    facts["warnings"] = notes
    scores, aligned = metrics_mod.evaluate(scene.points, recon.points, config["align"],
                                           streams["metrics"])
    scores.update(stress=float(recon.stress), iterations=int(recon.iterations),
                  runtime_s=float(recon.runtime_s), points_kept=len(scene.points))
    scores.update({f"seen_ge_{m}": n for m, n in enumerate(scene.seen_at_least, start=1)})
    if "unplaced" in recon.info:
        scores["unplaced"] = len(recon.info["unplaced"])
    if "rejected" in recon.info:  # refine: observations taken for corrupted
        scores["rejected"] = int(recon.info["rejected"])
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=aligned, facts=facts, wall_s=time.perf_counter() - start)


@dataclass
class RunRecord:
    """What a sweep worker sends back to the parent: small, picklable, no mesh.

    A run that raised is a record too (``status="FAILED"``, with the error),
    so one bad grid point never stops a sweep. ``code`` is the identity of the
    code that computed it (the worker's own, which on a cluster may differ
    from the parent's).
    """

    config_hash: str
    params: dict[str, Any]  # the flat config, as logged
    status: str  # FINISHED or FAILED, as MLflow names them
    start_ms: int
    end_ms: int
    code: str
    metrics: dict[str, float] = field(default_factory=dict)
    stress_history: np.ndarray | None = None
    facts: dict[str, str] = field(default_factory=dict)
    truth: np.ndarray | None = None  # ground truth, for the artifacts
    reconstruction: np.ndarray | None = None  # aligned to the truth
    picture: np.ndarray | None = None  # comparison.png's bytes (uint8), for the artifacts
    error: str = ""
    traceback: str = ""


ARRAY_FIELDS = ("stress_history", "truth", "reconstruction", "picture")  # kept out of JSON


def record_fields(record: RunRecord) -> dict[str, Any]:
    """A record's JSON-able fields (its arrays go elsewhere: the journal's .npz)."""
    return {k: v for k, v in vars(record).items() if k not in ARRAY_FIELDS}


def record_from_fields(fields: dict[str, Any], arrays: dict[str, np.ndarray]) -> RunRecord:
    return RunRecord(**fields, **{k: arrays.get(k) for k in ARRAY_FIELDS})


def _made_by(config: RunConfig) -> dict[str, Any]:
    """Which run a record is of, and the code that computed it."""
    return {"config_hash": config.hash(), "params": config.flat(), "code": code_identity()}


def failed_record(config: RunConfig, error: str, trace: str = "", start: float | None = None,
                  facts: dict[str, str] | None = None) -> RunRecord:
    """The record of a run that raised, or whose worker died."""
    now = time.time()
    return RunRecord(**_made_by(config), status="FAILED", start_ms=int((start or now) * 1000),
                     end_ms=int(now * 1000),
                     facts=facts or {}, error=error, traceback=trace)


def run_record(config: RunConfig, keep_clouds: bool = True) -> RunRecord:
    """Run ``config`` in a worker and return what the parent will log."""
    start = time.time()
    worker = {"worker": f"{socket.gethostname()}:{os.getpid()}"}
    try:
        result = run(config)
    except Exception as exc:  # noqa: BLE001 - any failure is this run's result, not the sweep's
        message = str(exc) if isinstance(exc, MpeError) else f"{type(exc).__name__}: {exc}"
        return failed_record(config, message or type(exc).__name__, traceback.format_exc(),
                             start, worker)
    recon = result.reconstruction
    facts = {**worker, "termination": recon.termination,
             "visible_per_view": ",".join(map(str, result.scene.visible_per_view))}
    if result.facts.get("warnings"):
        facts["warnings"] = " | ".join(result.facts["warnings"])
    keep_clouds = keep_clouds and len(result.aligned) > 0  # COLMAP may make no model
    picture = _picture(result) if keep_clouds else None
    if isinstance(picture, str):
        facts["picture_error"], picture = picture, None
    return RunRecord(**_made_by(config), status="FINISHED", start_ms=int(start * 1000),
                     end_ms=int(time.time() * 1000),
                     metrics={**result.metrics, "wall_s": result.wall_s},
                     stress_history=np.asarray(recon.stress_history, dtype=float), facts=facts,
                     truth=result.scene.points if keep_clouds else None,
                     reconstruction=result.aligned if keep_clouds else None, picture=picture)


def _title(result: RunResult) -> str:
    config = result.config
    if config["pipeline"] == "colmap":
        return (f"{config['shape']}  COLMAP, {config['images.count']} photos  "
                f"CD x100={result.metrics['cd_x100']:.3g}")
    return (f"{config['shape']}  N={config['points']}  K={config['views']}  {config['projections']}  "
            f"{config.solver}  ROA={result.metrics['roa']:.3g}")


def _picture(result: RunResult) -> np.ndarray | str:
    """The run's comparison picture as PNG bytes, drawn in the worker so the
    parent only stores it; a drawing failure is noted, never the run's."""
    from .render import comparison_png

    try:
        png = comparison_png(result.scene.points, result.aligned, _title(result))
    except Exception as exc:  # noqa: BLE001 - a picture is not worth a run
        return f"{type(exc).__name__}: {exc}"
    return np.frombuffer(png, dtype=np.uint8)


def write_outputs(result: RunResult, out: Path) -> list[Path]:
    """ground_truth.ply, reconstruction.ply (aligned) and a PNG comparing them."""
    import trimesh

    from .render import render_comparison

    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "ground_truth.ply", out / "reconstruction.ply", out / "comparison.png"]
    trimesh.PointCloud(result.scene.points).export(paths[0])
    if not len(result.aligned):  # COLMAP made no model: nothing to compare
        return paths[:1]
    trimesh.PointCloud(result.aligned).export(paths[1])
    render_comparison(result.scene.points, result.aligned, paths[2], title=_title(result))
    return paths
