"""The paper's pipeline: a sampled cloud seen through K projections, solved and scored."""

from __future__ import annotations

from typing import Any

from mpe3d import solvers
from mpe3d.harness.experiment.config import RunConfig
from mpe3d.harness.experiment.result import RunResult, short_number
from mpe3d.harness.scene import metrics
from mpe3d.harness.scene.observe import build_scene, observe
from mpe3d.solvers.degenerate import collect_notes


def run(config: RunConfig, streams) -> RunResult:
    """Scene, observations, solve, scores; the solver only ever sees the observations."""
    scene = build_scene(config, streams)
    observations, facts = observe(scene, config, streams)
    with collect_notes() as notes:
        recon = solvers.solve(config.solver, observations, init=config["init"],
                              random_state=streams["solver"], **config.solver_options)
    facts["warnings"] = notes
    scores, aligned = metrics.evaluate(scene.points, recon.points, config["align"],
                                           streams["metrics"])
    scores.update(stress=float(recon.stress), iterations=int(recon.iterations),
                  runtime_s=float(recon.runtime_s), points_kept=len(scene.points))
    scores.update({f"seen_ge_{m}": n for m, n in enumerate(scene.seen_at_least, start=1)})
    if "unplaced" in recon.info:
        scores["unplaced"] = len(recon.info["unplaced"])
    if "rejected" in recon.info:  # refine: observations taken for corrupted
        scores["rejected"] = int(recon.info["rejected"])
    return RunResult(config=config, metrics=scores, scene=scene, reconstruction=recon,
                     aligned=aligned, facts=facts)


def method_name(config) -> None:
    """A points run is named by its solver."""
    return None


def title(result: RunResult) -> str:
    config = result.config
    return (f"{config['shape']}  N={config['points']}  K={config['views']}  {config['projections']}  "
            f"{config.solver}  ROA={result.metrics['roa']:.3g}")


def describe(summary: dict[str, Any]) -> list[str]:
    cfg = summary["config"]
    return [f"shape {cfg['shape']}, N={cfg['points']}, K={cfg['views']}, "
            f"visibility {cfg['visibility']['mode']}, projections {cfg['projections']}, "
            f"solver {cfg['solver']['name']} (init {cfg['init']}), seed {cfg['seed']}",
            f"visible per view: {summary['visible_per_view']}",
            "  ".join(f"{k}={short_number(summary[k])}" for k in ("cd", "cd_mean", "emd", "emd_mean", "roa")),
            f"stress={short_number(summary['stress'])}  iterations={summary['iterations']} "
            f"({summary['termination']})  solver {summary['runtime_s']:.3f} s, "
            f"total {summary['wall_s']:.3f} s"]
