"""MLflow tracking: where runs live, which are already done, and logging results.

Only the parent process uses this module: workers return
:class:`~mpe3d.harness.experiment.execute.RunRecord` objects and the parent logs them here, one
by one as they arrive. The default store is MLflow's embedded SQLite database
``./mlflow.db`` with artifacts in ``./mlartifacts``; ``MLFLOW_TRACKING_URI`` or
an explicit URI (``sqlite:///...``, ``http://host:port``) points elsewhere.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import shutil
import socket
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from mpe3d.errors import DiskFull, MpeError, StoreError, first_line, suggest
from mpe3d.harness.files import cache_folder, failed_path, free_bytes, human_bytes, no_space
from mpe3d.harness.tracking.identity import code_identity, git_commit, is_current
from mpe3d.harness.tracking.ownership import STALE_S, Owner

DEFAULT_URI = "sqlite:///mlflow.db"
HASH_TAG = "mpe3d.config_hash"
CODE_TAG = "mpe3d.code"  # the identity of the code that computed a run
CLAIM_TAG = "mpe3d.claim"  # "<code>#<config hash>": one computation, claimed before it starts
OWNER_TAG = "mpe3d.owner"
HEARTBEAT_TAG = "mpe3d.heartbeat"
ERROR_TAG = "mpe3d.error"
UNRECORDED = "unrecorded"  # the code of runs tracked before runs carried their code identity
PARENT_TAG = "mlflow.parentRunId"
# Statuses in the order a resume trusts them: a FINISHED run of a config wins.
STATUS_RANK = {"FINISHED": 3, "FAILED": 2, "KILLED": 1, "RUNNING": 0, "SCHEDULED": 0}
# MLflow retries an unreachable server for minutes; a sweep must give up in
# well under 30 s (its results wait in the journal): at most 3 tries of 4 s and
# 3 s of back-off, so a hung server is given up on within 15 s.
HTTP_LIMITS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
               "MLFLOW_HTTP_REQUEST_TIMEOUT": "4"}
_UNREACHABLE = ("connection refused", "no answer in time")


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
    """Artifacts of a SQLite store go to ``mlartifacts`` beside the database
    (a server or file store decides for itself: None)."""
    database = _database(uri)
    return (Path(database).parent / "mlartifacts").as_uri() if database else None


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


def claim_key(code: str, config_hash: str) -> str:
    return f"{code}#{config_hash}"


def _quiet_mlflow() -> None:
    # MLflow and alembic log schema migrations at INFO on a new SQLite store;
    # urllib3 warns at every retry of a server that stopped answering, which
    # the one line of a StoreError says better.
    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)
    logging.getLogger("urllib3").setLevel(logging.ERROR)
    # The store logs each failed database call with its traceback, then raises
    # it: the raised error becomes our one line (a full disk, a lock).
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


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
    raise StoreError(f"cannot reach the MLflow tracking server at {uri}: {reason}")


@contextlib.contextmanager
def _store_errors(uri: str, action: str) -> Iterator[None]:
    """MLflow, SQLAlchemy and HTTP failures as one line naming the store."""
    try:
        yield
    except MpeError:
        raise
    except Exception as exc:  # noqa: BLE001 - the store's many error types, one message
        if no_space(exc):
            path = failed_path(exc) or _database(uri) or uri
            raise DiskFull(f"tracking store {uri}: cannot {action}: no space left at {path} "
                           f"({human_bytes(free_bytes(path))} free)", path) from None
        raise StoreError(f"tracking store {uri}: cannot {action}: {_reason(exc)}") from None


def _database(uri: str) -> str | None:
    return uri[len("sqlite:///"):] if uri.startswith("sqlite:///") else None


def _reason(exc: Exception) -> str:
    """The first line of a store error, without urllib3's retry narrative."""
    text = str(exc)
    for marker, reason in (("Connection refused", "connection refused"),
                           ("NewConnectionError", "connection refused"),
                           ("timed out", "no answer in time"),
                           ("database is locked", "the database is locked")):
        if marker in text:
            return reason
    return first_line(exc)


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock between processes on one machine (the SQLite store's)."""
    import fcntl

    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _open_sqlite(uri: str, database: Path):
    """A client on a SQLite store, creating the store if needed.

    Two processes creating one store at once would both run MLflow's schema
    migrations ("table experiments already exists"), so creation happens
    under a lock file beside the database. A new store is put in WAL mode:
    readers then never block the writers of a concurrent sweep.
    """

    lock = database.with_name(database.name + ".lock")
    made = _not_yet(database, lock)
    try:
        database.parent.mkdir(parents=True, exist_ok=True)
        with _file_lock(lock):
            new = not database.exists() or database.stat().st_size == 0
            client = _copied_store(uri, database) if new else None
            if client is None:
                client = _client(uri, database, new)
    except BaseException as exc:
        _remove(made)  # a failed opening leaves the user's folder as it was
        if isinstance(exc, OSError) and not no_space(exc):
            raise StoreError(f"tracking store {uri}: cannot open it: {exc.strerror or exc}") from None
        raise
    return client


def _client(uri: str, database: Path, new: bool):
    """MLflow's client on ``database``, which MLflow opens now: it makes the
    tables of an empty file, or checks a copied store's schema and adds its
    Default experiment. A ``new`` file is put in WAL mode first."""
    import sqlite3

    from mlflow.tracking import MlflowClient

    if new:
        with contextlib.closing(sqlite3.connect(database)) as connection:
            connection.execute("PRAGMA journal_mode=WAL")
    client = MlflowClient(tracking_uri=uri)
    client.search_experiments(max_results=1)
    return client


def _side_files(database: Path) -> list[Path]:
    """What SQLite keeps beside ``database``."""
    return [database.with_name(database.name + suffix) for suffix in ("-wal", "-shm", "-journal")]


def store_template() -> Path | None:
    """An empty store as MLflow makes it: its schema at the installed MLflow's
    head, no experiment in it (MLflow adds its Default experiment, with this
    store's artifact location, when it opens a copy). Made once per version of
    MLflow, SQLAlchemy and alembic, in the cache folder: MLflow's ~60 schema
    migrations cost a new store about a second; a copy is checked instead.
    None where the template cannot be made or kept."""
    import sqlite3

    import alembic
    import mlflow
    import sqlalchemy

    versions = f"{mlflow.__version__} {sqlalchemy.__version__} {alembic.__version__}"
    path = cache_folder() / f"mlflow-store-{hashlib.sha256(versions.encode()).hexdigest()[:16]}.db"
    if path.is_file():
        return path
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=".store-") as folder:
            made, part = Path(folder) / "made.db", Path(folder) / "template.db"
            _client(f"sqlite:///{made}", made, new=True)
            with contextlib.closing(sqlite3.connect(made)) as source, \
                    contextlib.closing(sqlite3.connect(part)) as copy:
                source.execute("DELETE FROM experiments")  # its Default's artifacts: under this cwd
                source.commit()
                source.backup(copy)  # the pages still in the write-ahead log too
            os.replace(part, path)  # whole or not at all, whoever makes it last
    except Exception:  # noqa: BLE001 - without a template, MLflow makes the store itself
        return None
    return path


def _copied_store(uri: str, database: Path):
    """A client on a new store copied from :func:`store_template`, or None
    (the copy removed, the template too) where there is none or MLflow
    refuses the copy; MLflow then makes the store itself."""

    template = store_template()
    if template is None:
        return None
    try:
        shutil.copyfile(template, database)
        return _client(uri, database, new=True)
    except Exception as exc:  # noqa: BLE001 - a damaged or foreign template: made again next time
        for path in (database, *_side_files(database)):
            path.unlink(missing_ok=True)
        if not no_space(exc):
            template.unlink(missing_ok=True)
        return None


def _not_yet(database: Path, lock: Path) -> list[Path]:
    """What opening ``database`` may create that is not there yet, deepest first:
    the store and its SQLite side files, the lock, the folders above them."""
    side = _side_files(database)
    folders, folder = [], database.parent
    while not folder.exists():
        folders.append(folder)
        folder = folder.parent
    return [p for p in (database, *side, lock) if not p.exists()] + folders


def _remove(paths: list[Path]) -> None:
    for path in paths:
        with contextlib.suppress(OSError):
            if path.is_dir():
                path.rmdir()  # only when empty: nothing of the user's goes
            else:
                path.unlink(missing_ok=True)


@dataclass
class Tracked:
    """What a store holds for one config, as a resume sees it."""

    status: str | None = None  # the best status of a run by the running code
    stale: int = 0  # FINISHED runs by other code
    known: set[str] = field(default_factory=set)  # their run ids: a later one is another sweep's


class Tracker:
    """An MLflow store, seen through what a sweep needs from it."""

    def __init__(self, uri: str | None = None, create: bool = True):
        self.uri = resolve_uri(uri)
        self.code = code_identity()
        path = _database(self.uri)
        database = Path(path) if path else None
        if database is not None and not create and not database.is_file():
            raise MpeError(f"no tracking store at {database} (run a sweep first, or pass "
                           "--tracking-uri / set MLFLOW_TRACKING_URI)")
        if self.uri.startswith(("http://", "https://")):
            for name, value in HTTP_LIMITS.items():
                os.environ.setdefault(name, value)
            _check_server(self.uri)
            # MLflow prints a "View run" link to stdout after every run it closes on a server.
            os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
        from mlflow.tracking import MlflowClient

        _quiet_mlflow()  # after the import: importing mlflow sets its own log level
        # run id -> its artifact location, from the run's creation: MLflow's
        # log_artifacts reads the whole run back to find it (9 of the parent's
        # 40 ms a run, which the workers of a 2-core sweep wait for)
        self._artifact_uris: dict[str, str] = {}

        with _store_errors(self.uri, "open it"):
            self.client = _open_sqlite(self.uri, database) if database is not None \
                else MlflowClient(tracking_uri=self.uri)

    def local_folders(self) -> list[Path]:
        """The folders of this machine the store writes to (its database, its artifacts)."""
        database = _database(self.uri)
        return [Path(database).parent, Path(database).parent / "mlartifacts"] if database else []

    def experiment_id(self, name: str, create: bool = True) -> str | None:
        """The id of experiment ``name``, created (if ``create``) when missing."""
        from mlflow.exceptions import MlflowException

        with _store_errors(self.uri, f"look up experiment '{name}'"):
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

    def tracked(self, experiment_id: str, codes: Mapping[str, str] | None = None) -> dict[str, Tracked]:
        """config hash -> what the store holds for it, judged by the running code
        (``codes``: each config's own, where a plug-in adds its part)."""
        codes = codes or {}
        out: dict[str, Tracked] = {}
        with _store_errors(self.uri, "read its runs"):
            for run in self._runs(experiment_id):
                key, status = run.data.tags.get(HASH_TAG), run.info.status
                if not key:
                    continue
                entry = out.setdefault(key, Tracked())
                if run.data.tags.get(CODE_TAG) != codes.get(key, self.code):
                    entry.stale += status == "FINISHED"
                    continue
                if status in ("FINISHED", "FAILED"):
                    entry.known.add(run.info.run_id)
                if STATUS_RANK.get(status, 0) > STATUS_RANK.get(entry.status, -1):
                    entry.status = status
        return out

    # -- claims: a config is a RUNNING run of its sweep before it is computed ---------

    def _child_tags(self, parent_id: str, config_hash: str, code: str, owner: Owner,
                    run_name: str) -> dict[str, str]:
        return {HASH_TAG: config_hash, CODE_TAG: code, CLAIM_TAG: claim_key(code, config_hash),
                PARENT_TAG: parent_id, OWNER_TAG: owner.tag(), "mlflow.runName": run_name}

    def claim(self, experiment_id: str, parent_id: str, config_hash: str, run_name: str,
              owner: Owner, known: set[str], code: str | None = None) -> tuple[str, Any]:
        """Try to own the computation of one config by the running code (``code``
        if a plug-in adds its part to it).

        Create our claim, then look for others: a run that FINISHED or FAILED
        since the plan (``known`` holds the ones before it) means another sweep
        did it; another live claim means another sweep is doing it. Either way
        ours is withdrawn. Two sweeps racing may both withdraw (and retry), but
        never both win: each looks only after its own claim is in the store.

        Returns ``("won", run_id)``, ``("busy", run)`` or ``("done", run)``.
        """
        code = code or self.code
        key = claim_key(code, config_hash)
        with _store_errors(self.uri, "claim a run"):
            run = self.client.create_run(experiment_id, run_name=run_name, tags=self._child_tags(
                parent_id, config_hash, code, owner, run_name))
            mine = run.info.run_id
            state, other = self._claim_state(experiment_id, key, known, mine)
            if state == "free":
                self._artifact_uris[mine] = run.info.artifact_uri
                return "won", mine
            self.client.delete_run(mine)
        return ("busy" if state == "busy" else "done"), other

    def claim_state(self, experiment_id: str, config_hash: str, known: set[str],
                    code: str | None = None) -> tuple[str, Any]:
        """``("done" | "busy" | "free", run)``: has another sweep computed this
        config since the plan, is one computing it, or may we claim it? A claim
        whose owner died is closed as KILLED here, and the config is free."""
        with _store_errors(self.uri, "read a claim"):
            return self._claim_state(experiment_id, claim_key(code or self.code, config_hash), known)

    def _claim_state(self, experiment_id, key, known, mine=None) -> tuple[str, Any]:
        runs = [r for r in self._runs(experiment_id, f"tags.`{CLAIM_TAG}` = '{key}'")
                if r.info.run_id != mine]
        done = [r for r in runs if r.info.status in ("FINISHED", "FAILED") and r.info.run_id not in known]
        if done:
            return "done", max(done, key=lambda r: STATUS_RANK[r.info.status])
        for run in runs:
            if run.info.status == "RUNNING" and not self._close_if_dead(run, {}):
                return "busy", run
        return "free", None

    def _heartbeat_of(self, run, running: dict[str, Any]) -> float | None:
        parent_id = run.data.tags.get(PARENT_TAG)
        parent = run if parent_id is None else running.get(parent_id)
        if parent is None:
            from mlflow.exceptions import MlflowException

            try:
                parent = self.client.get_run(parent_id)
            except MlflowException:
                return None
        beat = parent.data.tags.get(HEARTBEAT_TAG)
        return float(beat) if beat else None

    def _close_if_dead(self, run, running: dict[str, Any]) -> bool:
        """Close ``run`` as KILLED if its owner is dead; whether it was."""
        owner = Owner.parse(run.data.tags.get(OWNER_TAG))
        if owner is None:  # logged by a version of mpe3d without heartbeats
            dead = time.time() - run.info.start_time / 1000 > STALE_S
        else:
            dead = not owner.alive(self._heartbeat_of(run, running))
        if dead:
            self.kill([run.info.run_id], f"its sweep ({owner or 'unknown'}) died before the run ended")
        return dead

    def close_zombies(self, experiment_id: str) -> int:
        """Close every RUNNING run of ``experiment_id`` whose owner is dead
        (children and parents); returns how many children it closed."""
        with _store_errors(self.uri, "close the runs of dead sweeps"):
            running = {r.info.run_id: r for r in self._runs(experiment_id, "attributes.status = 'RUNNING'")}
            closed = [run for run in running.values() if self._close_if_dead(run, running)]
        return sum(HASH_TAG in run.data.tags for run in closed)

    def kill(self, run_ids, reason: str) -> None:
        """Close runs as KILLED, saying why."""
        for run_id in run_ids:
            self.client.set_tag(run_id, ERROR_TAG, reason)
            self.client.set_terminated(run_id, status="KILLED")

    # -- the sweep's parent run ---------------------------------------------------------

    def start_parent(self, experiment_id: str, sweep, tags: dict[str, str], owner: Owner) -> str:
        """The parent run of one sweep invocation."""
        from mpe3d import __version__

        commit = git_commit()
        tags = {"mpe3d.sweep_file": str(sweep.path), "mpe3d.sweep_sha256": sweep.sha256,
                "mpe3d.scale": sweep.scale, CODE_TAG: self.code,
                "mpe3d.version": __version__, "mpe3d.host": socket.gethostname(),
                OWNER_TAG: owner.tag(), HEARTBEAT_TAG: f"{time.time():.1f}",
                "mlflow.note.content": sweep.description, **tags}
        if commit:
            tags.update({"mpe3d.git_commit": commit, "mlflow.source.git.commit": commit})
        with _store_errors(self.uri, "start the sweep's parent run"):
            run = self.client.create_run(experiment_id, tags=tags,
                                         run_name=f"{sweep.name} {time.strftime('%Y-%m-%d %H:%M:%S')}")
        return run.info.run_id

    def heartbeat(self, parent_ids) -> None:
        """Tell other sweeps these parents' owner still lives."""
        now = f"{time.time():.1f}"
        with _store_errors(self.uri, "send a heartbeat"):
            for run_id in parent_ids:
                self.client.set_tag(run_id, HEARTBEAT_TAG, now)

    def finish_parent(self, run_id: str, status: str, counts: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        with _store_errors(self.uri, "close the sweep's parent run"):
            self.client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0)
                                                   for k, v in counts.items()])
            self.client.set_terminated(run_id, status=status, end_time=now)

    # -- results ----------------------------------------------------------------------

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
        with _store_errors(self.uri, "log a run"):
            try:
                self.client.log_batch(run_id, metrics=metrics, params=params,
                                      tags=[RunTag(k, v) for k, v in tags.items()])
                self.log_artifacts(run_id, record, artifacts)
            except BaseException as exc:  # interrupted half-way: never leave a run RUNNING,
                if _reason(exc) not in _UNREACHABLE:  # unless the store is gone: another try
                    with contextlib.suppress(Exception):  # would only wait for it again
                        self.client.set_terminated(run_id, status="KILLED")
                raise
            self.client.set_terminated(run_id, status=record.status, end_time=record.end_ms)

    def replay(self, entry) -> bool:
        """Log a journaled result left by a dead sweep; False if the store had it."""
        from mlflow.exceptions import MlflowException

        meta, record = entry.meta, entry.record
        with _store_errors(self.uri, "replay the journal"):
            try:
                claimed = self.client.get_run(meta["run_id"])
            except MlflowException:
                claimed = None
            if claimed is not None and claimed.info.status == "FINISHED":
                return False
            experiment_id = self.experiment_id(meta["experiment"])
            tags = self._child_tags(meta["parent_id"], record.config_hash, record.code,
                                    Owner.current(), meta["run_name"])
            run = self.client.create_run(experiment_id, start_time=record.start_ms, tags=tags,
                                         run_name=meta["run_name"])
            run_id = run.info.run_id
            self._artifact_uris[run_id] = run.info.artifact_uri
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
            location = self._artifact_uris.pop(run_id, None)
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
        with _store_errors(self.uri, "log the summary report"):
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
        with _store_errors(self.uri, "read its runs"):
            for run in self._runs(experiment_id):
                if HASH_TAG not in run.data.tags:  # a sweep's parent run
                    continue
                row = {"run_id": run.info.run_id, "status": run.info.status,
                       "config_hash": run.data.tags[HASH_TAG],
                       "start_time": pd.Timestamp(run.info.start_time, unit="ms"),
                       "error": run.data.tags.get(ERROR_TAG, ""),
                       "code": run.data.tags.get(CODE_TAG, UNRECORDED)}
                row.update(run.data.params)
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
