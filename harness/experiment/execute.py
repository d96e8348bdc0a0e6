"""One run end to end, through the pipeline its config names, and its record for the parent."""

from __future__ import annotations

import functools
import os
import socket
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import ThreadpoolController

from mpe3d import plugins
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import PIPELINE_NAMES, RENDERED, RunConfig
from mpe3d.harness.experiment.datasets import dataset_of
from mpe3d.harness.experiment.limits import check_run_memory
from mpe3d.harness.experiment.result import Pipeline, RunResult
from mpe3d.harness.scene.observe import seed_streams
from mpe3d.harness.tracking.identity import run_code
from mpe3d.harness.tracking.records import RunRecord
from mpe3d.solvers import threads

# BLAS sums in another order with another thread count, which moves results by
# an ulp or more; one thread everywhere (CLI, sweep parent, loky and dask
# workers) makes every run bit-identical wherever it runs. Sweeps get their
# parallelism from running several runs at once, so our own solver passes
# (whose bits do not depend on their thread count) take one thread too.
BLAS_THREADS = 1


# The keys each pipeline reads (a name ending in "." covers its dotted
# family): what a run logs as its MLflow params, so that a reader comparing
# runs sees the keys that shaped them. Its identity (config.hash) and its
# record keep every key.
PIPELINE_KEYS = {
    "points": ("pipeline", "seed", "shape", "points", "views", "angle_range", "view_layout",
               "visibility.", "noise.", "projections", "observe", "init", "align", "solver."),
    "colmap": ("pipeline", "seed", "shape", "points", "images."),
    "tracks": ("pipeline", "seed", "tracks.", "solver.name"),  # no option reaches its solvers
    # a folder's run reads no rendering key (config normalises them), a rendered set's does
    "photos": ("pipeline", "seed", "photos.", "shape", "images."),
}


def shaping_params(config: RunConfig) -> dict[str, Any]:
    """The keys of ``config`` its pipeline reads (:data:`PIPELINE_KEYS`), those
    left at None aside."""
    reads = PIPELINE_KEYS[config["pipeline"]]
    families = tuple(key for key in reads if key.endswith("."))
    return {key: value for key, value in config.flat().items()
            if value is not None and (key in reads or key.startswith(families))}


def pipeline(name: str) -> Pipeline:
    """What the ``pipeline`` key's value ``name`` runs, imported when first asked
    for: the colmap pipeline brings pycolmap and POT, which a run of the others
    need not load (seconds of every fresh process)."""
    if name == "points":
        from mpe3d.harness.experiment import points_pipeline as chosen
    elif name == "colmap":
        from mpe3d.harness.experiment import colmap_pipeline as chosen
    elif name == "tracks":
        from mpe3d.harness.experiment import tracks_pipeline as chosen
    elif name == "photos":
        from mpe3d.harness.experiment import photos_pipeline as chosen
    else:
        raise MpeError(f"pipeline: unknown pipeline '{name}' (use {' or '.join(PIPELINE_NAMES)})")
    return chosen


def expected_work(config: RunConfig) -> float:
    """A rough relative cost of a run, for ordering a sweep's runs longest
    first, so that no worker idles while the last long run finishes: a colmap
    run renders, matches and adjusts ``images.count`` photos (250: minutes); a
    points run's stress is K views of N^2 pairs, plus the N^2 EMD (1024
    points, 5 views: about a second); a tracks run solves a real data set
    (seconds). Only the order matters: the runs' results do not depend on it."""
    pipeline_name = config["pipeline"]
    if pipeline_name == "colmap":
        return 0.5 * config["images.count"]
    if pipeline_name == "tracks":
        return 2.0
    if pipeline_name == "photos":  # a folder: its photos are unknown until read; a dozen is typical
        return 0.5 * config["images.count"] if config["photos.set"] == RENDERED else 10.0
    n = config["points"] / 1024.0
    return n * n * (config["views"] + 1)


def run(config: RunConfig) -> RunResult:
    """Run ``config``; the solver only ever sees the observations."""
    if config["pipeline"] in ("points", "colmap"):  # a tracks or photos run samples no points
        check_run_memory(config)  # before sampling: refuse what cannot fit, in one line
    with _blas_limit(), threads.limit(BLAS_THREADS):
        return _run(config)


def _blas_limit():
    """threadpool_limits(BLAS_THREADS), without its scan of every loaded
    library on each run (5 ms in a worker, numba's and scipy's libraries
    loaded): the scan is made again only after an import, the only way a new
    BLAS or OpenMP library comes into a worker."""
    return _libraries(len(sys.modules)).limit(limits=BLAS_THREADS)


@functools.lru_cache(maxsize=1)
def _libraries(modules: int) -> ThreadpoolController:
    """threadpoolctl's view of the loaded libraries while ``modules`` modules are."""
    return ThreadpoolController()


def _run(config: RunConfig) -> RunResult:
    start = time.perf_counter()
    result = pipeline(config["pipeline"]).run(config, seed_streams(config["seed"]))
    return replace(result, wall_s=time.perf_counter() - start)


def code_of(config: RunConfig) -> str:
    """The identity of the code that computes ``config``: ours, and its plug-ins'."""
    if config["pipeline"] == "photos":
        return run_code(config.solver, config["shape"], sfm=config["photos.solver"])
    return run_code(config.solver, config["shape"])


def _made_by(config: RunConfig) -> dict[str, Any]:
    """Which run a record is of, and the code that computed it."""
    return {"config_hash": config.hash(), "params": shaping_params(config),
            "config": {key: str(value) for key, value in config.flat().items()},
            "dataset": dataset_of(config), "code": code_of(config)}


def failed_record(config: RunConfig, error: str, trace: str = "", start: float | None = None,
                  facts: dict[str, str] | None = None) -> RunRecord:
    """The record of a run that raised, or whose worker died."""
    now = time.time()
    return RunRecord(**_made_by(config), status="FAILED", start_ms=int((start or now) * 1000),
                     end_ms=int(now * 1000),
                     facts=facts or {}, error=error, traceback=trace)


def run_record(config: RunConfig, keep_clouds: bool = True, plugin_files=()) -> RunRecord:
    """Run ``config`` in a worker and return what the parent will log; the
    parent's plug-in files are loaded first (once per worker)."""
    start = time.time()
    worker = {"worker": f"{socket.gethostname()}:{os.getpid()}"}
    try:
        plugins.load_files(plugin_files)
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
    return pipeline(result.config["pipeline"]).title(result)


def _picture(result: RunResult) -> np.ndarray | str:
    """The run's comparison picture as PNG bytes, drawn in the worker so the
    parent only stores it; a drawing failure is noted, never the run's."""
    from mpe3d.harness.experiment.pictures import comparison_png

    try:
        png = comparison_png(result.scene.points, result.aligned, _title(result))
    except Exception as exc:  # noqa: BLE001 - a picture is not worth a run
        return f"{type(exc).__name__}: {exc}"
    return np.frombuffer(png, dtype=np.uint8)


def write_outputs(result: RunResult, out: Path) -> list[Path]:
    """ground_truth.ply, reconstruction.ply (aligned) and a PNG comparing them."""
    import trimesh

    from mpe3d.harness.experiment.pictures import draw_comparison

    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "ground_truth.ply", out / "reconstruction.ply", out / "comparison.png"]
    trimesh.PointCloud(result.scene.points).export(paths[0])
    if not len(result.aligned):  # COLMAP made no model: nothing to compare
        return paths[:1]
    trimesh.PointCloud(result.aligned).export(paths[1])
    draw_comparison(result.scene.points, result.aligned, paths[2], title=_title(result))
    return paths
