"""Where a tracking store is and how to reach it: its URI, the server check,
and every MLflow, SQLAlchemy or HTTP failure turned into one line naming it."""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Iterator

from mpe3d.errors import DiskFull, MpeError, StoreError, first_line
from mpe3d.harness.files import failed_path, free_bytes, human_bytes, no_space

DEFAULT_URI = "sqlite:///mlflow.db"
# MLflow retries an unreachable server for minutes; a sweep must give up in
# well under 30 s (its results wait in the journal): at most 3 tries of 4 s and
# 3 s of back-off, so a hung server is given up on within 15 s.
HTTP_LIMITS = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
               "MLFLOW_HTTP_REQUEST_TIMEOUT": "4"}
UNREACHABLE = ("connection refused", "no answer in time")


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
    database = database_path(uri)
    return (Path(database).parent / "mlartifacts").as_uri() if database else None


def quiet_mlflow() -> None:
    # MLflow and alembic log schema migrations at INFO on a new SQLite store;
    # urllib3 warns at every retry of a server that stopped answering, which
    # the one line of a StoreError says better.
    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)
    logging.getLogger("urllib3").setLevel(logging.ERROR)
    # The store logs each failed database call with its traceback, then raises
    # it: the raised error becomes our one line (a full disk, a lock).
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


def check_server(uri: str) -> None:
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
def store_errors(uri: str, action: str) -> Iterator[None]:
    """MLflow, SQLAlchemy and HTTP failures as one line naming the store."""
    try:
        yield
    except MpeError:
        raise
    except Exception as exc:  # noqa: BLE001 - the store's many error types, one message
        if no_space(exc):
            path = failed_path(exc) or database_path(uri) or uri
            raise DiskFull(f"tracking store {uri}: cannot {action}: no space left at {path} "
                           f"({human_bytes(free_bytes(path))} free)", path) from None
        raise StoreError(f"tracking store {uri}: cannot {action}: {reason(exc)}") from None


def database_path(uri: str) -> str | None:
    return uri[len("sqlite:///"):] if uri.startswith("sqlite:///") else None


def reason(exc: Exception) -> str:
    """The first line of a store error, without urllib3's retry narrative."""
    text = str(exc)
    for marker, reason in (("Connection refused", "connection refused"),
                           ("NewConnectionError", "connection refused"),
                           ("timed out", "no answer in time"),
                           ("database is locked", "the database is locked")):
        if marker in text:
            return reason
    return first_line(exc)
