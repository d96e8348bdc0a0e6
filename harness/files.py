"""Writing files so that a reader never sees half of one, nor half of a set."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any, Sequence


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


def atomic_write(path: str | Path, write) -> None:
    """``write(temp_path)``, then rename over ``path``: never a half-written file."""
    write_together([(Path(path), write)])
