"""Run records: what a worker sends back, and what the journal and MLflow keep of it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class RunRecord:
    """What a sweep worker sends back to the parent: small, picklable, no mesh.

    A run that raised is a record too (``status="FAILED"``, with the error),
    so one bad grid point never stops a sweep. ``code`` is the identity of the
    code that computed it (the worker's own, which on a cluster may differ
    from the parent's).
    """

    config_hash: str
    params: dict[str, Any]  # the keys that shaped the run: its MLflow params
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
    config: dict[str, str] = field(default_factory=dict)  # every key, as text (the reports read it)
    dataset: dict[str, str] = field(default_factory=dict)  # the data it read: an MLflow dataset's fields


ARRAY_FIELDS = ("stress_history", "truth", "reconstruction", "picture")  # kept out of JSON


def record_fields(record: RunRecord) -> dict[str, Any]:
    """A record's JSON-able fields (its arrays go elsewhere: the journal's .npz)."""
    return {k: v for k, v in vars(record).items() if k not in ARRAY_FIELDS}


def record_from_fields(fields: dict[str, Any], arrays: dict[str, np.ndarray]) -> RunRecord:
    return RunRecord(**fields, **{k: arrays.get(k) for k in ARRAY_FIELDS})
