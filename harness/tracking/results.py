"""Results into the store and out of it: a run's record logged (params,
metrics, the stress history, tags, artifacts), a journaled record replayed,
and an experiment's runs as a DataFrame. A mix-in of
:class:`~mpe3d.harness.tracking.store.Tracker`."""

from __future__ import annotations

import contextlib
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError, suggest
from mpe3d.harness.tracking.claims import (
    CLAIM_TAG,
    CODE_TAG,
    ERROR_TAG,
    HASH_TAG,
    STATUS_RANK,
    UNRECORDED,
    claim_key,
)
from mpe3d.harness.tracking.connection import UNREACHABLE, reason, store_errors
from mpe3d.harness.tracking.identity import git_commit, is_current
from mpe3d.harness.tracking.ownership import Owner

# Steps of the stress history logged as a metric: MLflow's SQLite store takes
# 0.35 ms a metric row, 0.1 s for SGD's 301 iterations, and the parent logs
# every run of a sweep while the workers wait on nothing but CPU it takes.
CHART_STEPS = 64


def chart_steps(n: int, most: int = CHART_STEPS) -> np.ndarray:
    """At most ``most`` of the steps 0..n-1, log-spaced (a descent's stress
    changes fastest early), the first and the last always among them."""
    if n <= most:
        return np.arange(n)
    steps = np.unique(np.round(np.geomspace(1, n, most)).astype(int) - 1)
    return np.union1d(steps, [0, n - 1])


CONFIG_TAG = "mpe3d.config"  # a run's every key, as JSON text: its params are those that shaped it
TAG_CHARS = 8000  # MLflow cuts a tag's value here (a warning, no error): a longer config goes in parts


def config_tags(config: dict[str, str]) -> dict[str, str]:
    """A run's config as tags: ``mpe3d.config``, then ``mpe3d.config.1``, ``.2``...
    for what does not fit in one tag."""
    text = json.dumps(config, sort_keys=True)
    parts = [text[i:i + TAG_CHARS] for i in range(0, len(text), TAG_CHARS)]
    return {CONFIG_TAG if i == 0 else f"{CONFIG_TAG}.{i}": part for i, part in enumerate(parts)}


def config_of(tags: dict[str, str]) -> dict[str, str]:
    """The config :func:`config_tags` wrote ({} for a run logged before it,
    or one whose tags were cut: its params then stand in)."""
    parts, i = [tags.get(CONFIG_TAG, "")], 1
    while f"{CONFIG_TAG}.{i}" in tags:
        parts.append(tags[f"{CONFIG_TAG}.{i}"])
        i += 1
    try:
        return json.loads("".join(parts)) if parts[0] else {}
    except json.JSONDecodeError:
        return {}
DATASET_CONTEXT = "input"  # a dataset input's mlflow.data.context: what the method reconstructs from


def dataset_input(fields: dict[str, str]):
    """A run's data set (the fields of :func:`mpe3d.harness.experiment.datasets.dataset_of`)
    as an MLflow dataset input."""
    from mlflow.entities import Dataset, DatasetInput, InputTag

    return DatasetInput(Dataset(**fields), tags=[InputTag("mlflow.data.context", DATASET_CONTEXT)])


class Results:
    """Logging and reading results. Mixed into the tracker, whose ``client``,
    ``uri``, ``code``, ``runs_of``, ``artifact_uris``, ``child_tags`` and
    ``experiment_id`` it uses."""

    def log_record(self, run_id: str, record, artifacts: bool = True) -> None:
        """Fill a claimed run with its result: params, metrics, stress history,
        tags, artifacts; then close it with the record's status."""
        from mlflow.entities import Metric, Param, RunTag

        tags = {CODE_TAG: record.code, CLAIM_TAG: claim_key(record.code, record.config_hash),
                **{f"mpe3d.{k}": str(v) for k, v in record.facts.items()}}
        commit = git_commit()
        if commit and is_current(record.code, self.code):
            tags["mpe3d.git_commit"] = commit
        if record.error:
            tags[ERROR_TAG] = record.error[:5000]
        t = record.end_ms
        metrics = [Metric(k, float(v), t, 0) for k, v in record.metrics.items()]
        if record.stress_history is not None:  # the stress by iteration, for MLflow's chart
            history = np.asarray(record.stress_history, dtype=float)
            metrics += [Metric("stress_history", float(history[i]), t, int(i))
                        for i in chart_steps(len(history))]
        params = [Param(k, str(v)) for k, v in record.params.items()]
        if record.config:
            tags.update(config_tags(record.config))
        with store_errors(self.uri, "log a run"):
            try:
                self.client.log_batch(run_id, metrics=metrics, params=params,
                                      tags=[RunTag(k, v) for k, v in tags.items()])
                if record.dataset:
                    self._log_dataset(run_id, record.dataset)
                self.log_artifacts(run_id, record, artifacts)
            except BaseException as exc:  # interrupted half-way: never leave a run RUNNING,
                if reason(exc) not in UNREACHABLE:  # unless the store is gone: another try
                    with contextlib.suppress(Exception):  # would only wait for it again
                        self.client.set_terminated(run_id, status="KILLED")
                raise
            self.client.set_terminated(run_id, status=record.status, end_time=record.end_ms)

    def _log_dataset(self, run_id: str, fields: dict[str, str]) -> None:
        """The run's data set, for the UI's Datasets column: a store that
        refuses it (a server older than MLflow 2.4) costs the run nothing but
        that column; a store gone is raised as every other write's."""
        from mlflow.exceptions import MlflowException

        try:
            self.client.log_inputs(run_id, datasets=[dataset_input(fields)])
        except MlflowException as exc:
            if reason(exc) in UNREACHABLE:
                raise
            warnings.warn(f"run {run_id}: its data set not logged ({str(exc).splitlines()[0][:200]})",
                          stacklevel=2)

    def replay(self, entry) -> bool:
        """Log a journaled result left by a dead sweep; False if the store had it."""
        from mlflow.exceptions import MlflowException

        meta, record = entry.meta, entry.record
        with store_errors(self.uri, "replay the journal"):
            try:
                claimed = self.client.get_run(meta["run_id"])
            except MlflowException:
                claimed = None
            if claimed is not None and claimed.info.status == "FINISHED":
                return False
            experiment_id = self.experiment_id(meta["experiment"])
            tags = self.child_tags(meta["parent_id"], record.config_hash, record.code,
                                    Owner.current(), meta["run_name"])
            run = self.client.create_run(experiment_id, start_time=record.start_ms, tags=tags,
                                         run_name=meta["run_name"])
            run_id = run.info.run_id
            self.artifact_uris[run_id] = run.info.artifact_uri
            self.log_record(run_id, record, artifacts=True)
            if claimed is not None and claimed.info.status == "RUNNING":
                self.client.delete_run(claimed.info.run_id)  # superseded by the replayed run
        return True

    def log_artifacts(self, run_id: str, record, artifacts: bool) -> None:
        with tempfile.TemporaryDirectory(prefix="mpe3d-") as folder:
            folder = Path(folder)
            if record.traceback:
                (folder / "error.txt").write_text(record.traceback)
            if artifacts and record.truth is not None:
                import trimesh

                # a data set of real tracks may have no reference points: no file, not an empty one
                for name, cloud in (("ground_truth", record.truth), ("reconstruction", record.reconstruction)):
                    if cloud is not None and len(cloud):
                        trimesh.PointCloud(cloud).export(folder / f"{name}.ply")
            if artifacts and record.stress_history is not None and len(record.stress_history) > 1:
                np.savetxt(folder / "stress_history.csv", np.asarray(record.stress_history, dtype=float),
                           fmt="%.17g", header="stress after each iteration (row 0: the start)")
            if artifacts and record.picture is not None:  # what MLflow's UI can show
                (folder / "comparison.png").write_bytes(np.asarray(record.picture, np.uint8).tobytes())
            location = self.artifact_uris.pop(run_id, None)
            if not any(folder.iterdir()):
                return
            if location is None:  # a run this tracker did not create
                self.client.log_artifacts(run_id, str(folder))
            else:
                from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

                get_artifact_repository(location, tracking_uri=self.uri).log_artifacts(str(folder))

    def log_parent_artifacts(self, run_id: str, folder, files=None) -> None:
        """A sweep's summary report on its parent run, under ``summary/``: the
        whole ``folder``, or only ``files`` in it (kept in their subfolders)."""
        with store_errors(self.uri, "log the summary report"):
            if files is None:
                self.client.log_artifacts(run_id, str(folder), "summary")
            for path in files or []:
                relative = Path(path).relative_to(folder).parent
                self.client.log_artifact(run_id, str(path), str(Path("summary") / relative))

    def runs_frame(self, experiment: str, history: bool = False):
        """The child runs of ``experiment`` as a DataFrame, with ``status``,
        ``config_hash``, ``run_id``, ``error``, every param and every metric.

        ``code`` is the identity of the code that computed each run
        (``unrecorded`` for runs older than code identities).

        One row per config: its best run (FINISHED, then FAILED, ...), by the
        running code where it has one, else the latest; ``history`` keeps
        every run ever made.
        """
        import pandas as pd

        experiment_id = self.experiment_id(experiment, create=False)
        if experiment_id is None:
            names = self.experiment_names()
            raise MpeError(f"no experiment '{experiment}' in {self.uri} "
                           f"(experiments: {', '.join(names) or 'none'})", hint=suggest(experiment, names))
        rows = []
        with store_errors(self.uri, "read its runs"):
            for run in self.runs_of(experiment_id):
                if HASH_TAG not in run.data.tags:  # a sweep's parent run
                    continue
                row = {"run_id": run.info.run_id, "status": run.info.status,
                       "config_hash": run.data.tags[HASH_TAG],
                       "start_time": pd.Timestamp(run.info.start_time, unit="ms"),
                       "error": run.data.tags.get(ERROR_TAG, ""),
                       "code": run.data.tags.get(CODE_TAG, UNRECORDED)}
                row.update(run.data.params)  # a run logged before CONFIG_TAG: every key a param
                row.update(config_of(run.data.tags))
                row.update({k: v for k, v in run.data.metrics.items() if k != "stress_history"})
                rows.append(row)
        frame = pd.DataFrame(rows)
        if frame.empty:
            return frame
        if not history:  # reruns (--force, --rerun-failed) leave older runs of a config behind
            rank = frame["status"].map(STATUS_RANK).fillna(0)
            current = frame["code"].map(lambda code: is_current(code, self.code))
            order = frame.assign(_rank=rank, _current=current).sort_values(
                ["_rank", "_current", "start_time"]).index
            frame = frame.loc[order].drop_duplicates("config_hash", keep="last").sort_index()
        for column in frame.columns:  # MLflow keeps params as text
            if not pd.api.types.is_numeric_dtype(frame[column]) \
                    and column not in ("run_id", "config_hash", "start_time", "code"):
                with contextlib.suppress(ValueError, TypeError):
                    frame[column] = pd.to_numeric(frame[column])
        return frame
