"""A SQLite store set up safely: made under a lock (two sweeps never run
MLflow's migrations at once), in WAL mode, copied from an empty template when
it is new, and opened read-only where its folder cannot be written."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from mpe3d.errors import StoreError
from mpe3d.harness.files import cache_folder, no_space


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


def read_only(database: Path) -> bool:
    """Whether an existing store cannot be written where it lies (a read-only
    mount, a folder or file the user may not write)."""
    return database.is_file() and not (os.access(database.parent, os.W_OK) and os.access(database, os.W_OK))


def read_only_uri(database: Path) -> str:
    """The SQLAlchemy URI that opens ``database`` for reading only: SQLite
    neither writes nor locks it, nor makes its WAL side files."""
    from urllib.parse import quote

    return f"sqlite:///file:{quote(str(database.resolve()))}?mode=ro&immutable=1&uri=true"


def open_sqlite(uri: str, database: Path, create: bool = True):
    """A client on a SQLite store, creating the store if needed (``create``).

    Two processes creating one store at once would both run MLflow's schema
    migrations ("table experiments already exists"), so creation happens
    under a lock file beside the database. A new store is put in WAL mode:
    readers then never block the writers of a concurrent sweep. A store that
    is only read (not ``create``) where it cannot be written is opened
    read-only, with no lock: a command that writes refuses it in one line.
    """
    if not create and read_only(database):
        return _client(read_only_uri(database), database, new=False)

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
