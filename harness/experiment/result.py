"""What one run produced, and what a pipeline must provide to produce it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Protocol

import numpy as np

from mpe3d import solvers
from mpe3d.harness.experiment.config import RunConfig
from mpe3d.harness.scene.observe import Scene
from mpe3d.harness.tracking.identity import run_code

METRIC_KEYS = ("cd", "cd_mean", "emd", "emd_mean", "roa", "stress", "iterations", "runtime_s")


@dataclass
class RunResult:
    """What a run produced: its config, metrics and the clouds behind them."""

    config: RunConfig
    metrics: dict[str, float]
    scene: Scene
    reconstruction: solvers.Reconstruction
    aligned: np.ndarray
    facts: dict[str, Any]
    wall_s: float = 0.0  # the whole run's, set by execute.run

    def summary(self) -> dict[str, Any]:
        """The JSON contract of ``mpe3d run --json``."""
        out: dict[str, Any] = {"config": self.config.nested(), "config_hash": self.config.hash()}
        out.update({k: self.metrics[k] for k in METRIC_KEYS if k in self.metrics})
        out.update({k: v for k, v in self.metrics.items() if k not in METRIC_KEYS})
        out["visible_per_view"] = self.scene.visible_per_view
        out["warnings"] = self.facts.get("warnings", [])
        out["termination"] = self.reconstruction.termination
        out["wall_s"] = self.wall_s
        sfm = self.config["photos.solver"] if self.config["pipeline"] == "photos" else None
        out["code"] = run_code(self.config.solver, self.config["shape"], sfm=sfm)
        return out


def short_number(value) -> str:
    """A metric as ``mpe3d run`` prints it: 4 significant digits for a float."""
    return f"{value:.4g}" if isinstance(value, float) else str(value)


class Pipeline(Protocol):
    """A way from a run's config to its scores, chosen by the ``pipeline`` key.

    A module of :mod:`mpe3d.harness.experiment` with these three functions,
    listed in :func:`mpe3d.harness.experiment.execute.pipeline`.
    """

    def run(self, config: RunConfig, streams: dict[str, np.random.Generator]) -> RunResult:
        """The run, its random draws from ``streams`` (one per stage)."""

    def title(self, result: RunResult) -> str:
        """One line naming the run, over its comparison picture."""

    def describe(self, summary: dict[str, Any]) -> list[str]:
        """The lines ``mpe3d run`` prints of :meth:`RunResult.summary`."""

    def method_name(self, config: Mapping[str, Any]) -> str | None:
        """The method a run of ``config`` is named by in tables and figures;
        None: its solver's (the reports label the paper's solvers)."""

