"""The sweep files that ship with mpe3d: ``quick.yaml`` and the paper's, ``paper/*.yaml``.

They are package data, so an installed mpe3d finds them without the
repository (``mpe3d reproduce-paper`` runs the paper's).

May import: nothing of mpe3d.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["paper_sweeps"]


def paper_sweeps() -> list[Path]:
    """The paper's sweep files, one per experiment, in a stable order."""
    folder = Path(str(files(__name__) / "paper"))
    return sorted(folder.glob("*.yaml"))
