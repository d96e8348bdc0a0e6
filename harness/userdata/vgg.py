"""VGG's multi-view files (Oxford Visual Geometry Group: Model House, Merton College, ...).

A data set is a set of text files beside each other:

* ``<name>.nview-corners``: one line per track, one token per view, the
  0-based index of the track's corner in that view's corner file, or ``*``
  where the view does not see it;
* ``<name>.<k>.corners`` (``k`` 3 digits from 000), one ``x y`` line per
  corner in view k's image (older sets: ``nview-corners`` with
  ``001.corners``, ``002.corners``, ... counted from 001);
* optionally ``<name>.<k>.P``, view k's 3x4 camera matrix, and
  ``<name>.p3d``, one ``x y z`` line per track: VGG's own reconstruction,
  a reference for scoring and never an input of a solve.

The track's id is its line number (from 0). The files are found by content
(a text of equal-length rows of indices and stars) and by these names beside
it; every error is one line naming the file and the row.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError

MAX_BYTES = 200 * 2**20  # a track table larger than this is not a hand-matched data set
_TOKEN = re.compile(r"^(\*|\d+)$")


def sniff(path: Path) -> bool:
    """Whether ``path`` is an ``nview-corners`` table: so named (then a damaged
    one is read, to say where it is damaged), or whatever its name, its first
    lines (2 or more) are rows of the same count (2 or more) of corner indices
    and stars."""
    if path.name.endswith("nview-corners"):
        return True
    with open(path, "rb") as handle:
        block = handle.read(4096)
    lines = block.decode("utf-8", "replace").splitlines()
    if len(block) == 4096 and len(lines) > 1:
        lines = lines[:-1]  # the read may have cut the last line
    rows = [line.split() for line in lines[:20] if line.strip()]
    # two rows at least: a BAL header alone is a row of three integers too
    return len(rows) >= 2 and len(rows[0]) >= 2 and all(
        len(row) == len(rows[0]) and all(_TOKEN.match(t) for t in row) for row in rows)


def _stem(path: Path) -> str:
    name = path.name
    return name[:-len(".nview-corners")] if name.endswith(".nview-corners") else ""


def view_file(path: Path, k: int, suffix: str) -> Path | None:
    """View k's ``.corners`` or ``.P`` file beside ``path``: ``<name>.<k:03>``
    (from 000), or ``<k+1:03>`` (from 001) for a table without a name."""
    stem = _stem(path)
    names = [f"{stem}.{k:03d}{suffix}"] if stem else [f"{k + 1:03d}{suffix}", f"{k:03d}{suffix}"]
    for name in names:
        if (path.parent / name).is_file():
            return path.parent / name
    return None


def points_file(path: Path) -> Path | None:
    """The ``.p3d`` reference points beside ``path``: ``<name>.p3d``, or ``p3d``
    here or in ``../3D`` (the layout of the older sets)."""
    stem = _stem(path)
    for candidate in ([path.parent / f"{stem}.p3d"] if stem else
                      [path.parent / "p3d", path.parent.parent / "3D" / "p3d"]):
        if candidate.is_file():
            return candidate
    return None


def _table(path: Path) -> np.ndarray:
    """The track table: (tracks, views) corner indices, -1 where unseen."""
    if path.stat().st_size > MAX_BYTES:
        raise MpeError(f"{path}: {path.stat().st_size / 2**20:.0f} MiB, over the "
                       f"{MAX_BYTES // 2**20} MiB of a track table")
    rows = []
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            tokens = line.split()
            if not tokens:
                continue
            if rows and len(tokens) != len(rows[0]):
                raise MpeError(f"{path}: row {number} has {len(tokens)} entries, row 1 has "
                               f"{len(rows[0])} (one per view)")
            bad = next((t for t in tokens if not _TOKEN.match(t)), None)
            if bad is not None:
                raise MpeError(f"{path}: row {number}: '{bad[:20]}' is neither a corner index nor *")
            rows.append([-1 if t == "*" else int(t) for t in tokens])
    if not rows:
        raise MpeError(f"{path}: empty file")
    return np.array(rows, dtype=np.int64)


def _matrix(path: Path, columns: int, what: str) -> np.ndarray:
    """A whitespace table of finite numbers with ``columns`` per row."""
    try:
        values = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise MpeError(f"{path}: not a table of numbers ({str(exc).splitlines()[0][:80]})") from None
    if values.size == 0:
        raise MpeError(f"{path}: empty file")
    if values.shape[1] != columns:
        raise MpeError(f"{path}: {values.shape[1]} numbers a row, expected {columns} ({what})")
    if not np.isfinite(values).all():
        row = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise MpeError(f"{path}: row {row + 1} holds a number that is not finite")
    return values


def read_nview(path: str | Path) -> list[dict]:
    """The views of an ``nview-corners`` data set as ``{name, ids, xy}`` dicts."""
    path = Path(path)
    table = _table(path)
    views = []
    for k in range(table.shape[1]):
        corners_path = view_file(path, k, ".corners")
        if corners_path is None:
            expected = f"{_stem(path)}.{k:03d}.corners" if _stem(path) else f"{k + 1:03d}.corners"
            raise MpeError(f"{path}: view {k}'s corner file {expected} is not beside it")
        corners = _matrix(corners_path, 2, "x y")
        seen = np.flatnonzero(table[:, k] >= 0)
        index = table[seen, k]
        if len(index) and index.max() >= len(corners):
            row = int(seen[np.argmax(index)])
            raise MpeError(f"{path}: row {row + 1}, view {k}: corner {index.max()} but "
                           f"{corners_path.name} has {len(corners)}")
        views.append({"name": corners_path.stem, "ids": seen, "xy": corners[index]})
    return [view for view in views if len(view["ids"])]


def read_reference(path: str | Path) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict[str, np.ndarray] | None]:
    """The data set's reference, where it has one: its points (ids as text, and
    (N, 3)) from the ``.p3d`` file, and its cameras from the ``.P`` files (all
    views', or None), each 3x4 by its view's name (the name
    :func:`read_nview` gives the view: the files' stem)."""
    path = Path(path)
    table = _table(path)
    p3d = points_file(path)
    truth = None
    if p3d is not None:
        points = _matrix(p3d, 3, "x y z")
        if len(points) != len(table):
            raise MpeError(f"{p3d}: {len(points)} points for the {len(table)} tracks of {path.name}")
        truth = (np.arange(len(points)).astype(str), points)
    files = [view_file(path, k, ".P") for k in range(table.shape[1])]
    if any(f is None for f in files):
        return truth, None
    cameras = np.stack([_matrix(f, 4, "a 3x4 camera") for f in files])
    if cameras.shape[1:] != (3, 4):
        raise MpeError(f"{files[0]}: a camera matrix must have 3 rows of 4")
    return truth, {f.name.removesuffix(".P"): P for f, P in zip(files, cameras)}


def companions(path: str | Path) -> list[Path]:
    """Every file the data set of ``path`` reads: what identifies it."""
    path = Path(path)
    table = _table(path)
    found = [view_file(path, k, suffix) for suffix in (".corners", ".P") for k in range(table.shape[1])]
    return [f for f in [*found, points_file(path)] if f is not None]
