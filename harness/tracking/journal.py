"""The local journal: every computed run is on disk before it goes to the store.

The parent writes each result here the moment it arrives and removes it once
the tracking store has it, so a store outage, a crash or a ``kill -9`` between
computing and logging never loses a result. The next sweep against the same
store replays what its dead writers left behind, before it plans anything.

An entry is ``<id>.npz`` (the arrays) and ``<id>.json`` (everything else,
written last, so a half-written entry is never read). Nothing in it is
pickled: replaying a journal runs no code from it.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from mpe3d.errors import DiskFull
from mpe3d.harness.files import atomic_write, free_bytes, human_bytes, no_space
from mpe3d.harness.tracking.ownership import STALE_S, Owner
from mpe3d.harness.tracking.records import ARRAY_FIELDS, record_fields, record_from_fields

FOLDER = "mpe3d-journal"


@dataclass
class Entry:
    """One journaled result: where it belongs in the store, and the record."""

    path: Path  # the .json file
    meta: dict  # uri, experiment, experiment_id, parent_id, run_id, run_name, owner
    record: object  # an execute.RunRecord

    @property
    def arrays(self) -> Path:
        return self.path.with_suffix(".npz")


class Journal:
    """The journal folder of one working directory."""

    def __init__(self, folder: str | Path | None = None):
        self.folder = Path(folder) if folder else Path.cwd() / FOLDER

    def write(self, record, meta: dict) -> Entry:
        """Put ``record`` on disk (atomically) before it is logged."""
        path = self.folder / f"{os.getpid()}-{uuid.uuid4().hex[:12]}.json"
        arrays = {k: getattr(record, k) for k in ARRAY_FIELDS if getattr(record, k) is not None}

        def save_arrays(temp: Path) -> None:
            with open(temp, "wb") as handle:  # np.savez(name) would append .npz to the temp name
                np.savez(handle, **arrays)
        text = json.dumps({"meta": meta, "record": record_fields(record)})
        try:
            for attempt in range(3):  # another sweep in this folder may tidy it away meanwhile
                self.folder.mkdir(parents=True, exist_ok=True)
                try:
                    atomic_write(path.with_suffix(".npz"), save_arrays)
                    atomic_write(path, lambda temp: temp.write_text(text))
                    break
                except FileNotFoundError:
                    if attempt == 2:
                        raise
        except OSError as exc:
            path.with_suffix(".npz").unlink(missing_ok=True)  # half an entry is no entry
            if no_space(exc):
                raise DiskFull(f"cannot journal a computed run: no space left at {self.folder} "
                               f"({human_bytes(free_bytes(self.folder))} free)", str(self.folder)) from None
            raise
        return Entry(path, meta, record)

    def remove(self, entry: Entry) -> None:
        entry.path.unlink(missing_ok=True)
        entry.arrays.unlink(missing_ok=True)

    def tidy(self) -> None:
        """Remove the folder when nothing waits in it (a writer re-creates it)."""
        with contextlib.suppress(OSError):
            self.folder.rmdir()

    def orphans(self, uri: str) -> Iterator[Entry]:
        """Entries for store ``uri`` whose writer is dead, each taken by this
        process (renamed) so that two replaying sweeps never log one twice."""
        if not self.folder.is_dir():
            return
        me = os.getpid()
        for path, data in self._entries(uri):
            if self._writer_alive(data["meta"], path):
                continue
            taken = path.with_name(f"{me}-{uuid.uuid4().hex[:12]}.json")
            try:
                os.rename(path.with_suffix(".npz"), taken.with_suffix(".npz"))
                os.rename(path, taken)
            except FileNotFoundError:  # another sweep took it first
                continue
            data["meta"]["owner"] = Owner.current().tag()  # others now see a live writer
            atomic_write(taken, lambda temp, text=json.dumps(data): temp.write_text(text))
            try:
                with np.load(taken.with_suffix(".npz"), allow_pickle=False) as arrays:
                    loaded = {k: arrays[k] for k in arrays.files}
            except (OSError, ValueError):  # damaged: leave it for a person to look at
                continue
            yield Entry(taken, data["meta"], record_from_fields(data["record"], loaded))

    @staticmethod
    def _writer_alive(meta: dict, path: Path) -> bool:
        """By pid on this host; an entry of another host's (a shared folder)
        lives seconds unless its writer could not log it, so age tells there."""
        owner = Owner.parse(meta.get("owner"))
        if owner is None or owner.pid == os.getpid():
            return False
        if owner.host == socket.gethostname():
            return owner.alive(None)
        return time.time() - path.stat().st_mtime < STALE_S

    def pending(self, uri: str) -> int:
        """How many entries for ``uri`` wait to be replayed."""
        return sum(1 for _ in self._entries(uri))

    def _entries(self, uri: str) -> Iterator[tuple[Path, dict]]:
        """The readable entries for ``uri``: their .json paths and contents."""
        if not self.folder.is_dir():
            return
        for path in sorted(self.folder.glob("*.json")):
            try:
                data = json.loads(path.read_text())
            except (OSError, ValueError):  # being written or taken by another process
                continue
            if data.get("meta", {}).get("uri") == uri:
                yield path, data
