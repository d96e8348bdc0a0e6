"""Writing files so that a reader never sees half of one, nor half of a set."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

# How a full disk reads in SQLite's and the OS's messages, where no errno survives.
_FULL_DISK_TEXTS = ("database or disk is full", "No space left on device", "Disk quota exceeded")


def write_together(files: Sequence[tuple[Path, Any]]) -> None:
    """Write several files as one unit, each ``(path, write(temp_path))``: all
    are written to temporary files first, then renamed into place; if a step
    fails, what was already in place is put back. Both, or neither."""
    pid = os.getpid()
    temps = [path.with_name(f".{path.name}.{pid}.tmp") for path, _ in files]
    backups = [path.with_name(f".{path.name}.{pid}.old") for path, _ in files]
    placed: list[int] = []
    try:
        for (_, write), temp in zip(files, temps):
            write(temp)
        for i, ((path, _), temp) in enumerate(zip(files, temps)):
            if path.exists() and i < len(files) - 1:  # the last rename cannot need undoing
                _keep_copy(path, backups[i])
            os.replace(temp, path)  # atomic: a reader sees the old file or the new one
            placed.append(i)
    except BaseException:
        for i in reversed(placed):
            path = files[i][0]
            path.unlink(missing_ok=True)
            if backups[i].exists():
                os.replace(backups[i], path)
        raise
    finally:
        for leftover in (*temps, *backups):
            leftover.unlink(missing_ok=True)


def _keep_copy(path: Path, backup: Path) -> None:
    try:
        os.link(path, backup)  # the original stays in place meanwhile
    except OSError:
        shutil.copy2(path, backup)


def cache_folder() -> Path:
    """Where mpe3d keeps what it can always make again: ``$XDG_CACHE_HOME/mpe3d``
    (``~/.cache/mpe3d``). Its users read it tolerantly and may fail to write it."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mpe3d"


def atomic_write(path: str | Path, write) -> None:
    """``write(temp_path)``, then rename over ``path``: never a half-written file."""
    write_together([(Path(path), write)])


def _chain(exc: BaseException | None):
    """``exc`` and the exceptions it was raised from or during, once each."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def no_space(exc: BaseException | None) -> bool:
    """Whether ``exc``, or an exception it was raised from, is a full disk."""
    return any((isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT))
               or any(text in str(e) for text in _FULL_DISK_TEXTS) for e in _chain(exc))


def failed_path(exc: BaseException | None) -> str | None:
    """The file an OSError in ``exc``'s chain was writing (a copy's destination)."""
    return next((str(e.filename2 or e.filename) for e in _chain(exc)
                 if isinstance(e, OSError) and (e.filename2 or e.filename)), None)


def existing(path: str | Path) -> Path:
    """``path``, or its nearest folder that exists."""
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def free_bytes(path: str | Path) -> int:
    """Free space, in bytes, on the filesystem that holds ``path``."""
    return shutil.disk_usage(existing(path)).free


def same_device(a: str | Path, b: str | Path) -> bool:
    return os.stat(existing(a)).st_dev == os.stat(existing(b)).st_dev


def human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


class SpaceMeter:
    """Free space on the filesystems of ``paths`` when a sweep starts, to tell
    how much more its remaining runs need when one of them fills up."""

    def __init__(self, paths):
        self.start: dict[str, int] = {}
        for path in paths:
            try:
                self.start[str(path)] = free_bytes(path)
            except OSError:
                continue

    def needed(self, path: str | Path, done: int, left: int) -> int | None:
        """Bytes ``left`` more runs take at ``path``, at the rate of the ``done``
        so far; None when nothing was measured there."""
        for start, free in self.start.items():
            try:
                if same_device(start, path):
                    used = free - free_bytes(path)
                    return int(used / done * left) if done and used > 0 else None
            except OSError:
                continue
        return None


class Reserve:
    """``size`` bytes held in ``folder`` while a sweep runs, given back when that
    disk fills: closing the stopped sweep's runs (KILLED, the parent's counts)
    needs room too, and a SQLite store that cannot write them leaves them RUNNING.
    A disk already too full to hold the reserve simply gets none."""

    def __init__(self, folder: str | Path | None, size: int = 1 << 20):
        self.path: Path | None = None
        if folder is None:
            return
        path = Path(folder) / ".mpe3d-reserve"
        try:
            with open(path, "wb") as handle:
                os.posix_fallocate(handle.fileno(), 0, size)  # blocks taken now, not on write
        except (OSError, AttributeError):  # no room, or a system without fallocate
            path.unlink(missing_ok=True)
            return
        self.path = path

    def release(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)
            self.path = None
