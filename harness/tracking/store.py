"""MLflow tracking: where runs live, which are already done, and logging results.

Only the parent process uses this module: workers return
:class:`~mpe3d.harness.tracking.records.RunRecord` objects and the parent logs them here, one
by one as they arrive. The default store is MLflow's embedded SQLite database
``./mlflow.db`` with artifacts in ``./mlartifacts``; ``MLFLOW_TRACKING_URI`` or
an explicit URI (``sqlite:///...``, ``http://host:port``) points elsewhere.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterator

from mpe3d.errors import MpeError
from mpe3d.harness.tracking.claims import (
    CLAIM_TAG,
    CODE_TAG,
    ERROR_TAG,
    HASH_TAG,
    HEARTBEAT_TAG,
    OWNER_TAG,
    PARENT_TAG,
    STATUS_RANK,
    UNRECORDED,
    Claims,
    Tracked,
    claim_key,
)
from mpe3d.harness.tracking.connection import (
    DEFAULT_URI,
    HTTP_LIMITS,
    artifact_root,
    check_server,
    database_path,
    quiet_mlflow,
    resolve_uri,
    store_errors,
)
from mpe3d.harness.tracking.identity import code_identity
from mpe3d.harness.tracking.results import CHART_STEPS, Results, chart_steps
from mpe3d.harness.tracking.sqlite import open_sqlite, read_only, read_only_uri, store_template

NOTE_TAG = "mlflow.note.content"  # what MLflow's UI shows as an experiment's (or run's) description
NOTE_CHARS = 20000  # the longest experiment tag MLflow takes

__all__ = ["CHART_STEPS", "CLAIM_TAG", "CODE_TAG", "DEFAULT_URI", "ERROR_TAG", "HASH_TAG", "HEARTBEAT_TAG",
           "OWNER_TAG", "PARENT_TAG", "STATUS_RANK", "UNRECORDED", "Tracked", "Tracker", "artifact_root",
           "chart_steps", "claim_key", "resolve_uri", "serving_uri", "store_template"]


def serving_uri(uri: str) -> str:
    """The URI a reader (the MLflow UI) opens ``uri``'s store by: a SQLite
    store that cannot be written where it lies opens read-only."""
    path = database_path(uri)
    return read_only_uri(Path(path)) if path and read_only(Path(path)) else uri


class Tracker(Claims, Results):
    """An MLflow store, seen through what a sweep needs from it."""

    def __init__(self, uri: str | None = None, create: bool = True):
        self.uri = resolve_uri(uri)
        self.code = code_identity()
        path = database_path(self.uri)
        database = Path(path) if path else None
        if database is not None and not create and not database.is_file():
            raise MpeError(f"no tracking store at {database} (run a sweep first, or pass "
                           "--tracking-uri / set MLFLOW_TRACKING_URI)")
        if self.uri.startswith(("http://", "https://")):
            for name, value in HTTP_LIMITS.items():
                os.environ.setdefault(name, value)
            check_server(self.uri)
            # MLflow prints a "View run" link to stdout after every run it closes on a server.
            os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        from mlflow.tracking import MlflowClient

        quiet_mlflow()  # after the import: importing mlflow sets its own log level
        # run id -> its artifact location, from the run's creation: MLflow's
        # log_artifacts reads the whole run back to find it (9 of the parent's
        # 40 ms a run, which the workers of a 2-core sweep wait for)
        self.artifact_uris: dict[str, str] = {}

        with store_errors(self.uri, "open it"):
            self.client = open_sqlite(self.uri, database, create) if database is not None \
                else MlflowClient(tracking_uri=self.uri)

    def local_folders(self) -> list[Path]:
        """The folders of this machine the store writes to (its database, its artifacts)."""
        database = database_path(self.uri)
        return [Path(database).parent, Path(database).parent / "mlartifacts"] if database else []

    def experiment_id(self, name: str, create: bool = True) -> str | None:
        """The id of experiment ``name``, created (if ``create``) when missing."""
        from mlflow.exceptions import MlflowException

        with store_errors(self.uri, f"look up experiment '{name}'"):
            found = self.client.get_experiment_by_name(name)
            if found is not None and found.lifecycle_stage == "deleted":
                raise MpeError(f"experiment '{name}' is deleted in {self.uri}; restore it "
                               "(mlflow experiments restore) or rename the sweep")
            if found is not None:
                return found.experiment_id
            if not create:
                return None
            try:
                return self.client.create_experiment(name, artifact_location=artifact_root(self.uri))
            except MlflowException:  # another sweep created it a moment ago
                found = self.client.get_experiment_by_name(name)
                if found is None:
                    raise
                return found.experiment_id

    def describe(self, experiment_id: str, description: str) -> None:
        """Show ``description`` (a sweep's) on the experiment's page in the UI
        (its ``mlflow.note.content`` tag), when it says something new."""
        if not description:
            return
        description = description[:NOTE_CHARS]
        with store_errors(self.uri, "describe an experiment"):
            found = self.client.get_experiment(experiment_id)
            if found.tags.get(NOTE_TAG) != description:
                self.client.set_experiment_tag(experiment_id, NOTE_TAG, description)

    def experiment_names(self) -> list[str]:
        with store_errors(self.uri, "list experiments"):
            return [e.name for e in self.client.search_experiments()]

    def runs_of(self, experiment_id: str, filter_string: str = "") -> Iterator[Any]:
        token = None
        while True:
            page = self.client.search_runs([experiment_id], filter_string=filter_string,
                                           max_results=5000, page_token=token)
            yield from page
            token = page.token
            if not token:
                return
