"""A sweep's own summary (its table and figures) on its MLflow parent run."""

from __future__ import annotations

import tempfile
from pathlib import Path

from mpe3d.reports import paper
from mpe3d.reports.load import runs


def log_sweep_summary(tracker, sweep, parent_id: str) -> None:
    """Draw ``sweep``'s section of the report from its tracked runs and log it
    as artifacts of the parent run ``parent_id``."""
    frame = runs(tracker, sweep.name, hashes=[c.hash() for c in sweep.runs])
    section = paper.Section(sweep.name, frame, sweep.description,
                            f"{sweep.path.name} --scale {sweep.scale}",
                            planned=len(sweep.runs), varying=sweep.varying)
    with tempfile.TemporaryDirectory(prefix="mpe3d-summary-") as folder:
        paper.write(Path(folder), [section], f"mpe3d sweep: {sweep.name}", claims=False, pdf=False)
        tracker.log_parent_artifacts(parent_id, folder)
