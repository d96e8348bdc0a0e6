"""MLflow tracking: where runs live, which are already done, and logging results.

Only the parent process uses this module: workers return
:class:`~harness.execute.RunRecord` objects and the parent logs them here, one
by one as they arrive. The default store is MLflow's embedded SQLite database
``./mlflow.db`` with artifacts in ``./mlartifacts``; ``MLFLOW_TRACKING_URI`` or
an explicit URI (``sqlite:///...``, ``http://host:port``) points elsewhere.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from .errors import MpeError, suggest

DEFAULT_URI = "sqlite:///mlflow.db"
HASH_TAG = "mpe3d.config_hash"
PARENT_TAG = "mlflow.parentRunId"
# Statuses in the order a resume trusts them: a FINISHED run of a config wins.
_STATUS_RANK = {"FINISHED": 3, "FAILED": 2, "KILLED": 1, "RUNNING": 0, "SCHEDULED": 0}


def resolve_uri(uri: str | None = None) -> str:
    """``uri``, else ``$MLFLOW_TRACKING_URI``, else ``sqlite:///mlflow.db``.

    A relative SQLite path is made absolute, so the store does not move when
    the working directory does.
    """
    uri = uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        uri = "sqlite:///" + str(Path(uri[len("sqlite:///"):]).resolve())
    return uri


def artifact_root(uri: str) -> str | None:
    """Artifacts of a SQLite store go to ``mlartifacts`` beside the database."""
    if uri.startswith("sqlite:///"):
        return (Path(uri[len("sqlite:///"):]).parent / "mlartifacts").as_uri()
    return None  # a server or file store decides for itself


def _quiet_mlflow() -> None:
    # MLflow and alembic log schema migrations at INFO on a new SQLite store.
    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _check_server(uri: str) -> None:
    """Fail in seconds, not after MLflow's minutes of retries, if no server answers."""
    import requests

    try:
        requests.get(uri.rstrip("/") + "/health", timeout=10).raise_for_status()
    except requests.HTTPError as exc:
        reason = f"its /health answered HTTP {exc.response.status_code}"
    except requests.Timeout:
        reason = "no answer within 10 s"
    except requests.RequestException:
        reason = "nothing answers there (is `mlflow server` running?)"
    else:
        return
    raise MpeError(f"cannot reach the MLflow tracking server at {uri}: {reason}")


@contextlib.contextmanager
def _store_errors(uri: str, action: str) -> Iterator[None]:
    """MLflow, SQLAlchemy and HTTP failures as one line naming the store."""
    try:
        yield
    except MpeError:
        raise
    except Exception as exc:  # noqa: BLE001 - the store's many error types, one message
        text = str(exc).strip().splitlines()
        reason = text[0][:300] if text else type(exc).__name__
        raise MpeError(f"tracking store {uri}: cannot {action}: {reason}") from None


def code_version(near: Path) -> str | None:
    """The git commit of the checkout holding ``near`` (``+dirty`` if modified)."""
    folder = near if near.is_dir() else near.parent
    try:
        commit = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"],
                                capture_output=True, text=True, timeout=10)
        if commit.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(folder), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return commit.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


class Tracker:
    """An MLflow store, seen through what a sweep needs from it."""

    def __init__(self, uri: str | None = None, create: bool = True):
        self.uri = resolve_uri(uri)
        database = Path(self.uri[len("sqlite:///"):]) if self.uri.startswith("sqlite:///") else None
        if database is not None and not create and not database.is_file():
            raise MpeError(f"no tracking store at {database} (run a sweep first, or pass "
                           "--tracking-uri / set MLFLOW_TRACKING_URI)")
        if self.uri.startswith(("http://", "https://")):
            _check_server(self.uri)
            # MLflow prints a "View run" link to stdout after every run it closes on a server.
            os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        from mlflow.tracking import MlflowClient

        _quiet_mlflow()  # after the import: importing mlflow sets its own log level

        with _store_errors(self.uri, "open it"):
            self.client = MlflowClient(tracking_uri=self.uri)

    def experiment_id(self, name: str, create: bool = True) -> str | None:
        """The id of experiment ``name``, created (if ``create``) when missing."""
        with _store_errors(self.uri, f"look up experiment '{name}'"):
            found = self.client.get_experiment_by_name(name)
            if found is not None and found.lifecycle_stage == "deleted":
                raise MpeError(f"experiment '{name}' is deleted in {self.uri}; restore it "
                               "(mlflow experiments restore) or rename the sweep")
            if found is not None:
                return found.experiment_id
            if not create:
                return None
            return self.client.create_experiment(name, artifact_location=artifact_root(self.uri))

    def experiment_names(self) -> list[str]:
        with _store_errors(self.uri, "list experiments"):
            return [e.name for e in self.client.search_experiments()]

    def _runs(self, experiment_id: str, filter_string: str = "") -> Iterator[Any]:
        token = None
        while True:
            page = self.client.search_runs([experiment_id], filter_string=filter_string,
                                           max_results=5000, page_token=token)
            yield from page
            token = page.token
            if not token:
                return

    def tracked(self, experiment_id: str) -> dict[str, str]:
        """config hash -> the best status any run of that config reached."""
        best: dict[str, str] = {}
        with _store_errors(self.uri, "read its runs"):
            for run in self._runs(experiment_id):
                key = run.data.tags.get(HASH_TAG)
                status = run.info.status
                if key and _STATUS_RANK.get(status, 0) > _STATUS_RANK.get(best.get(key), -1):
                    best[key] = status
        return best

    def start_parent(self, experiment_id: str, sweep, tags: dict[str, str]) -> str:
        """The parent run of one sweep invocation."""
        from . import __version__

        commit = code_version(sweep.path.resolve())
        tags = {"mpe3d.sweep_file": str(sweep.path), "mpe3d.sweep_sha256": sweep.sha256,
                "mpe3d.scale": sweep.scale,
                "mpe3d.version": __version__, "mpe3d.host": socket.gethostname(),
                "mlflow.note.content": sweep.description, **tags}
        if commit:
            tags.update({"mpe3d.git_commit": commit, "mlflow.source.git.commit": commit})
        with _store_errors(self.uri, "start the sweep's parent run"):
            run = self.client.create_run(experiment_id, tags=tags,
                                         run_name=f"{sweep.name} {time.strftime('%Y-%m-%d %H:%M:%S')}")
        return run.info.run_id

    def finish_parent(self, run_id: str, status: str, counts: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        with _store_errors(self.uri, "close the sweep's parent run"):
            self.client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0)
                                                   for k, v in counts.items()])
            self.client.set_terminated(run_id, status=status, end_time=now)

    def log_record(self, experiment_id: str, parent_id: str, record, run_name: str,
                   artifacts: bool = True) -> str:
        """One child run: params, metrics, stress history, tags, artifacts."""
        from mlflow.entities import Metric, Param, RunTag

        config = record.config
        tags = {HASH_TAG: config.hash(), PARENT_TAG: parent_id,
                **{f"mpe3d.{k}": str(v) for k, v in record.facts.items()}}
        if record.error:
            tags["mpe3d.error"] = record.error[:5000]
        t = record.end_ms
        metrics = [Metric(k, float(v), t, 0) for k, v in record.metrics.items()]
        if record.stress_history is not None:  # the per-iteration stress, as steps
            metrics += [Metric("stress_history", float(v), t, i)
                        for i, v in enumerate(record.stress_history)]
        params = [Param(k, str(v)) for k, v in config.flat().items()]
        with _store_errors(self.uri, "log a run"):
            run = self.client.create_run(experiment_id, start_time=record.start_ms, tags=tags,
                                         run_name=run_name)
            run_id = run.info.run_id
            try:
                self.client.log_batch(run_id, metrics=metrics, params=params,
                                      tags=[RunTag("mlflow.runName", run_name)])
                self._log_artifacts(run_id, record, artifacts)
            except BaseException:  # interrupted half-way: never leave a run RUNNING
                with contextlib.suppress(Exception):
                    self.client.set_terminated(run_id, status="KILLED")
                raise
            self.client.set_terminated(run_id, status=record.status, end_time=record.end_ms)
        return run_id

    def _log_artifacts(self, run_id: str, record, artifacts: bool) -> None:
        with tempfile.TemporaryDirectory(prefix="mpe3d-") as folder:
            folder = Path(folder)
            if record.traceback:
                (folder / "error.txt").write_text(record.traceback)
            if artifacts and record.truth is not None:
                import trimesh

                trimesh.PointCloud(record.truth).export(folder / "ground_truth.ply")
                trimesh.PointCloud(record.reconstruction).export(folder / "reconstruction.ply")
            if any(folder.iterdir()):
                self.client.log_artifacts(run_id, str(folder))

    def runs_frame(self, experiment: str, history: bool = False):
        """The child runs of ``experiment`` as a DataFrame, with ``status``,
        ``config_hash``, ``run_id``, ``error``, every param and every metric.

        One row per config (its latest FINISHED run, else its latest run),
        unless ``history`` asks for every run ever made.
        """
        import pandas as pd

        experiment_id = self.experiment_id(experiment, create=False)
        if experiment_id is None:
            names = self.experiment_names()
            raise MpeError(f"no experiment '{experiment}' in {self.uri} "
                           f"(experiments: {', '.join(names) or 'none'})", hint=suggest(experiment, names))
        rows = []
        with _store_errors(self.uri, "read its runs"):
            for run in self._runs(experiment_id):
                if HASH_TAG not in run.data.tags:  # a sweep's parent run
                    continue
                row = {"run_id": run.info.run_id, "status": run.info.status,
                       "config_hash": run.data.tags[HASH_TAG],
                       "start_time": pd.Timestamp(run.info.start_time, unit="ms"),
                       "error": run.data.tags.get("mpe3d.error", "")}
                row.update(run.data.params)
                row.update({k: v for k, v in run.data.metrics.items() if k != "stress_history"})
                rows.append(row)
        frame = pd.DataFrame(rows)
        if frame.empty:
            return frame
        if not history:  # reruns (--force, --rerun-failed) leave older runs of a config behind
            rank = frame["status"].map(_STATUS_RANK).fillna(0)
            order = frame.assign(_rank=rank).sort_values(["_rank", "start_time"]).index
            frame = frame.loc[order].drop_duplicates("config_hash", keep="last").sort_index()
        for column in frame.columns:  # MLflow keeps params as text
            if not pd.api.types.is_numeric_dtype(frame[column]) \
                    and column not in ("run_id", "config_hash", "start_time"):
                with contextlib.suppress(ValueError, TypeError):
                    frame[column] = pd.to_numeric(frame[column])
        return frame
