"""Reconstruct your own data: matched 2D keypoints (or distance matrices) -> a 3D cloud.

Inputs (checked hard at this boundary, every error one line naming the file,
view and row):

* CSV, long format with a header ``view,point,x,y``: one row per observation;
* NPZ with ``view<k>_ids`` and ``view<k>_xy`` or ``view<k>_dist`` arrays, or
  a folder with one ``<name>.npz`` per view holding ``ids`` and ``xy`` or
  ``dist``;
* JSON ``{"views": [{"ids": [...], "xy": [[x, y], ...]} | {"ids": [...], "dist": [[...]]}]}``.

Known projections (the fixed setting) come as a ``.npy`` or ``.json`` of K
matrices, 2x3 with orthonormal rows or 3x3 rotations, in view order.
"""

from __future__ import annotations

import csv
import json
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mpe3d import solvers
from mpe3d.solvers import Observations, View
from mpe3d.solvers.degenerate import collect_notes

from ..errors import MpeError, first_line
from .files import atomic_write, write_together
from .identity import code_identity

INPUT_FORMATS = (".csv", ".npz", ".json")
OUTPUT_FORMATS = (".ply", ".csv", ".npy")
SOLVERS = ("refine", "factorize", "sgd")
SYMMETRY_TOL = 1e-6  # relative: distance matrices written as text lose a little
ORTHONORMAL_TOL = 1e-6


@dataclass
class Result:
    """A reconstruction of user data: the cloud, its ids, and what to trust about it."""

    points: np.ndarray  # (N, 3), in the frame of the given projections when fixed
    ids: np.ndarray  # (N,) the input's point ids, in the order of ``points``
    projections: np.ndarray  # (K, 2, 3), given or estimated
    report: dict[str, Any] = field(default_factory=dict)


# -- reading -------------------------------------------------------------------

def _finite(values: np.ndarray, where: str, what: str) -> np.ndarray:
    try:
        values = np.asarray(values)
    except ValueError:  # ragged nested lists
        raise MpeError(f"{where}: {what} rows differ in length") from None
    if values.dtype.kind not in "iuf":  # text, booleans, complex, objects: never numbers here
        raise MpeError(f"{where}: {what} holds a non-numeric value ({values.dtype})")
    values = values.astype(np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argwhere(bad)[0][0])
        raise MpeError(f"{where}: {what} row {row} is not a finite number")
    return values


def _check_header(path: Path) -> None:
    """pandas renames a repeated column (``x``, ``x.1``) and reads the first: refuse instead."""
    with open(path, newline="", encoding="utf-8") as handle:
        header = [name.strip() for name in next(csv.reader(handle), [])]
    for i, name in enumerate(header):
        if not name and len(header) > 1:
            raise MpeError(f"{path}: the header has no name for column {i + 1} "
                           "(it must be view,point,x,y)")
        if name in header[:i]:
            raise MpeError(f"{path}: the header names column '{name}' twice "
                           f"(columns {header.index(name) + 1} and {i + 1})")


def _read_csv(path: Path) -> list[dict]:
    import pandas as pd

    try:
        _check_header(path)
        frame = pd.read_csv(path, dtype={"view": str, "point": str}, keep_default_na=False)
    except pd.errors.EmptyDataError:
        raise MpeError(f"{path}: empty file") from None
    except (pd.errors.ParserError, UnicodeDecodeError, csv.Error) as exc:
        raise MpeError(f"{path}: not a UTF-8 CSV file ({first_line(exc)})") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    for column in ("view", "point", "x", "y"):
        if column not in frame.columns:
            raise MpeError(f"{path}: missing column '{column}' (the header must be view,point,x,y)")
    if frame.empty:
        raise MpeError(f"{path}: empty file (a header and no rows)")
    for column in ("x", "y"):
        numbers = pd.to_numeric(frame[column], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(numbers))
        if len(bad):
            row = int(bad[0])
            raise MpeError(f"{path}: row {row + 2}: {column} is not a finite number "
                           f"({str(frame[column].iloc[row])!r})")
        frame[column] = numbers
    twice = frame.duplicated(["view", "point"], keep="first")
    if twice.any():
        row = int(np.flatnonzero(twice)[0])
        view, point = frame["view"].iloc[row], frame["point"].iloc[row]
        first = int(np.flatnonzero((frame["view"] == view) & (frame["point"] == point))[0])
        raise MpeError(f"{path}: row {row + 2}: point '{point}' appears twice in view '{view}' "
                       f"(first at row {first + 2})")
    views = []
    for name, group in frame.groupby("view", sort=False):
        views.append({"name": str(name), "ids": group["point"].to_numpy(),
                      "xy": group[["x", "y"]].to_numpy()})
    return views


def _view_from_arrays(arrays, name: str, where: str) -> dict:
    if "ids" not in arrays:
        raise MpeError(f"{where}: missing array 'ids'")
    has_xy, has_dist = "xy" in arrays, "dist" in arrays
    if has_xy == has_dist:
        raise MpeError(f"{where}: give exactly one of 'xy' and 'dist'")
    view = {"name": name, "ids": np.asarray(arrays["ids"]).ravel()}
    view["xy" if has_xy else "dist"] = np.asarray(arrays["xy" if has_xy else "dist"])
    return view


def _npz_members(path: Path) -> dict[str, np.ndarray]:
    """Every array of an NPZ file, read now: a truncated member, a bad CRC or an
    object array fails here, naming the member, not later inside a solver."""
    import zipfile

    from mpe3d.solvers.base import require_memory

    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise MpeError(f"{path}: not an NPZ file ({first_line(exc)})") from None
    members = {}
    with archive:
        for name in archive.files:
            try:
                require_memory(_declared_bytes(archive.zip, name), f"{path}: member '{name}'")
                members[name] = archive[name]
            except MpeError:
                raise
            except ValueError as exc:
                reason = "holds Python objects, which are never unpickled" \
                    if "allow_pickle" in str(exc) else first_line(exc)
                raise MpeError(f"{path}: member '{name}' {reason}") from None
            except MemoryError:
                raise MpeError(f"{path}: member '{name}' does not fit in memory") from None
            except Exception as exc:  # noqa: BLE001 - zlib, zipfile, EOF: a damaged archive
                raise MpeError(f"{path}: member '{name}' cannot be read (damaged or truncated: "
                               f"{type(exc).__name__})") from None
    return members


def _declared_bytes(archive, name: str) -> int:
    """The size a member's .npy header declares, read before its data."""
    try:
        with archive.open(name + ".npy") as handle:
            read = {(1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0}[np.lib.format.read_magic(handle)]
            shape, _, dtype = read(handle)
    except Exception:  # noqa: BLE001 - reading the member itself will say what is wrong
        return 0
    return int(np.prod(shape, dtype=np.float64) * dtype.itemsize)


def _read_npz(path: Path) -> list[dict]:
    data = _npz_members(path)
    names = sorted({key.split("_", 1)[0] for key in data if "_" in key},
                   key=lambda v: (len(v), v))
    if not names:
        if set(data) & {"ids", "xy", "dist"}:  # one view per file, inside a folder
            return [_view_from_arrays(data, path.stem, str(path))]
        raise MpeError(f"{path}: empty file (no view<k>_ids arrays)")
    return [_view_from_arrays({key.split("_", 1)[1]: data[key] for key in data
                               if key.startswith(f"{name}_")}, name, f"{path}: {name}")
            for name in names]


def _read_folder(path: Path) -> list[dict]:
    files = sorted(path.glob("*.npz"))
    if not files:
        raise MpeError(f"{path}: a folder input needs one .npz file per view (ids, and xy or dist)")
    views = []
    for file in files:
        views += _read_npz(file)
    return views


def _json_ids(value, where: str) -> list:
    if not isinstance(value, list) or not all(
            isinstance(v, (int, str)) and not isinstance(v, bool) for v in value):
        raise MpeError(f"{where}: ids must be a list of integers or strings")
    return value


def _json_matrix(value, where: str, what: str) -> np.ndarray:
    """A list of equal-length rows of numbers (``null`` becomes NaN, caught later)."""
    if not isinstance(value, list):
        raise MpeError(f"{where}: {what} must be a list of rows")
    for row_index, row in enumerate(value):
        if not isinstance(row, list):
            raise MpeError(f"{where}: {what} row {row_index} is not a list")
        if len(row) != len(value[0]):
            raise MpeError(f"{where}: {what} row {row_index} has {len(row)} entries, "
                           f"row 0 has {len(value[0])}")
        for item in row:
            if isinstance(item, bool) or not isinstance(item, (int, float, type(None))):
                kind = "true/false" if isinstance(item, bool) else type(item).__name__
                raise MpeError(f"{where}: {what} holds a non-numeric value (row {row_index}: {kind})")
    try:
        return np.array(value, dtype=np.float64)
    except OverflowError:
        raise MpeError(f"{where}: {what} holds a number too large for a float") from None


def _read_json(path: Path) -> list[dict]:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise MpeError(f"{path}: not a UTF-8 text file") from None
    if not text.strip():
        raise MpeError(f"{path}: empty file")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MpeError(f"{path}: malformed JSON at line {exc.lineno}: {exc.msg}") from None
    except RecursionError:
        raise MpeError(f"{path}: JSON nested too deeply") from None
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise MpeError(f"{path}: expected an object with a list 'views'")
    views = []
    for k, item in enumerate(data["views"]):
        where = f"{path}: view '{k}'"
        if not isinstance(item, dict):
            raise MpeError(f"{where}: expected an object with 'ids' and 'xy' or 'dist'")
        arrays = {key: _json_matrix(item[key], where, key) for key in ("xy", "dist") if key in item}
        if "ids" in item:
            arrays["ids"] = np.asarray(_json_ids(item["ids"], where), dtype=object).astype(str)
        views.append(_view_from_arrays(arrays, str(k), where))
    return views


def read_views(path: str | Path) -> list[dict]:
    """The views of an input file as dicts ``{name, ids, xy | dist}``, not yet checked."""
    path = Path(path)
    if path.is_dir():
        return _read_folder(path)
    if not path.exists():
        raise MpeError(f"{path}: no such file")
    if not path.is_file():
        raise MpeError(f"{path}: not a regular file")
    readers = {".csv": _read_csv, ".npz": _read_npz, ".json": _read_json}
    reader = readers.get(path.suffix.lower())
    if reader is None:
        raise MpeError(f"{path}: unknown input format '{path.suffix}' (expected .csv, .npz, "
                       ".json, or a folder of .npz files)")
    if path.stat().st_size == 0:
        raise MpeError(f"{path}: empty file")
    return reader(path)


def read_projections(path: str | Path) -> np.ndarray:
    """``(K, 2, 3)`` projections from a .npy or .json file of 2x3 or 3x3 matrices."""
    path = Path(path)
    if path.suffix.lower() not in (".npy", ".json"):
        raise MpeError(f"{path}: unknown projections format '{path.suffix}' (expected .npy or .json)")
    try:
        if path.stat().st_size == 0:
            raise MpeError(f"{path}: empty file")
        data = np.load(path, allow_pickle=False) if path.suffix.lower() == ".npy" \
            else json.loads(path.read_text())
    except OSError as exc:
        raise MpeError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except (ValueError, EOFError) as exc:
        raise MpeError(f"{path}: not a {path.suffix} array file ({first_line(exc)})") from None
    except RecursionError:
        raise MpeError(f"{path}: JSON nested too deeply") from None
    mats = []
    for k, m in enumerate(data if isinstance(data, list) or np.ndim(data) == 3 else [data]):
        m = _finite(m, f"{path}: projection {k}", "matrix")
        if m.shape not in ((2, 3), (3, 3)):
            raise MpeError(f"{path}: projection {k} is {'x'.join(map(str, m.shape))}, "
                           "expected 2x3 (orthonormal rows) or 3x3 (a rotation)")
        error = np.abs(m @ m.T - np.eye(len(m))).max()
        if error > ORTHONORMAL_TOL:
            raise MpeError(f"{path}: projection {k}: rows are not orthonormal "
                           f"(largest |P P^T - I| entry {error:.2g})")
        mats.append(m[:2])
    return np.stack(mats)


# -- checking ------------------------------------------------------------------

def _check_dist(D: np.ndarray, n: int, where: str) -> np.ndarray:
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise MpeError(f"{where}: dist is {'x'.join(map(str, D.shape))}, not square")
    if D.shape[0] != n:
        raise MpeError(f"{where}: dist is {D.shape[0]}x{D.shape[0]} but ids has {n} entries; "
                       "they must match")
    D = _finite(D, where, "dist")
    scale = max(float(np.abs(D).max()), 1e-300)
    asymmetry = float(np.abs(D - D.T).max())
    if asymmetry > SYMMETRY_TOL * scale:
        i, j = np.unravel_index(int(np.argmax(np.abs(D - D.T))), D.shape)
        raise MpeError(f"{where}: dist is not symmetric (row {i}, column {j}: {D[i, j]:.6g} vs "
                       f"{D[j, i]:.6g})")
    if (D < 0).any():
        i, j = np.argwhere(D < 0)[0]
        raise MpeError(f"{where}: dist has a negative entry (row {i}, column {j}: {D[i, j]:.6g})")
    if np.abs(np.diag(D)).max() > SYMMETRY_TOL * scale:
        i = int(np.argmax(np.abs(np.diag(D))))
        raise MpeError(f"{where}: dist has a non-zero diagonal (row {i}: {D[i, i]:.6g})")
    return 0.5 * (D + D.T)


def observations_from(views: Sequence[dict], projections=None, source: str = "input",
                      projections_source: str = "projections"):
    """Check user views and turn them into :class:`mpe3d.solvers.Observations`.

    Returns the observations and the point ids (index -> the user's id).
    """
    if len(views) < 2:
        raise MpeError(f"{source}: {len(views)} view(s); reconstruction needs at least 2")
    if projections is not None and len(projections) != len(views):
        raise MpeError(f"{projections_source}: {len(projections)} matrices for {len(views)} views")
    labels = [np.asarray(v["ids"]).astype(str) for v in views]
    for k, (view, ids) in enumerate(zip(views, labels)):
        where = f"{source}: view '{view.get('name', k)}'"
        if len(ids) < 3:
            raise MpeError(f"{where} has {len(ids)} point(s); each view needs at least 3")
        unique, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            raise MpeError(f"{where}: point '{unique[counts > 1][0]}' appears twice")
    all_ids, index = np.unique(np.concatenate(labels), return_inverse=True)
    out, start = [], 0
    for k, (view, ids) in enumerate(zip(views, labels)):
        where = f"{source}: view '{view.get('name', k)}'"
        rows = index[start:start + len(ids)]
        start += len(ids)
        if "xy" in view:
            xy = _finite(view["xy"], where, "xy")
            if xy.shape != (len(ids), 2):
                raise MpeError(f"{where}: xy is {'x'.join(map(str, xy.shape))}, expected "
                               f"{len(ids)}x2 (one row per id)")
            out.append(View(ids=rows, coordinates=xy))
        else:
            D = _check_dist(np.asarray(view["dist"]), len(ids), where)
            out.append(View(ids=rows, distances=D))
    obs = Observations(n_points=len(all_ids), views=tuple(out), projections=projections)
    return obs, _as_ids(all_ids, source)


def _as_ids(labels: np.ndarray, source: str) -> np.ndarray:
    """Integer ids back to integers; anything else stays text."""
    try:
        numbers = labels.astype(np.int64)
    except ValueError:
        return labels
    except OverflowError:
        big = next(label for label in labels if _overflows(label))
        raise MpeError(f"{source}: point id '{big}' is an integer too large for 64 bits; "
                       "use ids below 2**63, or text ids") from None
    return numbers if np.array_equal(numbers.astype(str), labels) else labels


def _overflows(label: str) -> bool:
    try:
        return abs(int(label)) >= 2 ** 63
    except ValueError:
        return False


# -- solving -------------------------------------------------------------------

@dataclass
class Problem:
    """User input, read and checked: what the solve needs, nothing computed yet."""

    observations: Observations
    ids: np.ndarray
    solver: str
    loss: str
    random_state: Any


def _check_random_state(random_state) -> None:
    if isinstance(random_state, np.random.Generator):
        return
    if isinstance(random_state, bool) or not isinstance(random_state, (int, np.integer)) \
            or random_state < 0:
        raise MpeError(f"random_state: expected an integer >= 0 or a numpy Generator, "
                       f"got {random_state!r}")


def prepare(views: Sequence[dict] | str | Path, projections=None, solver: str = "refine",
            loss: str = "l2", random_state=0) -> Problem:
    """Read and check every input of :func:`reconstruct` without solving anything."""
    if solver not in SOLVERS:
        raise MpeError(f"solver: '{solver}' is not one of {', '.join(SOLVERS)}")
    if loss != "l2" and solver != "refine":
        raise MpeError(f"loss='{loss}' needs solver='refine' (got solver='{solver}')")
    _check_random_state(random_state)
    source = str(views) if isinstance(views, (str, Path)) else "views"
    if isinstance(views, (str, Path)):
        views = read_views(views)
    projections_source = "projections"
    if isinstance(projections, (str, Path)):
        projections_source, projections = str(projections), read_projections(projections)
    elif projections is not None:
        projections = np.asarray(projections, dtype=float)[:, :2]
    obs, ids = observations_from(views, projections, source, projections_source)
    return Problem(obs, ids, solver, loss, random_state)


def solve(problem: Problem) -> Result:
    """Solve a prepared problem (paper Eq. 1) and report on the result."""
    options = {"loss": problem.loss} if problem.solver == "refine" else {}
    start = time.perf_counter()
    with collect_notes() as notes:  # notes about the input go in the report
        rec = solvers.solve(problem.solver, problem.observations,
                            random_state=problem.random_state, **options)
    runtime = time.perf_counter() - start
    report = _report(problem.observations, rec, problem.ids, problem.solver, problem.loss, runtime)
    report["warnings"] = notes
    return Result(points=rec.points, ids=problem.ids, projections=np.asarray(rec.projections),
                  report=report)


def reconstruct(views: Sequence[dict] | str | Path, projections=None, solver: str = "refine",
                loss: str = "l2", random_state=0) -> Result:
    """Rebuild a 3D cloud from user views (paper Eq. 1, fixed or variable setting).

    Parameters
    ----------
    views : a path (CSV, NPZ, JSON, folder) or a list of ``{"ids", "xy" | "dist"}`` dicts
        What each view saw: its point ids and their 2D coordinates or distance matrix.
    projections : None, a path, or an array of K 2x3 / 3x3 matrices, default None
        Known projections (fixed setting); None estimates them (variable setting).
    solver : {"refine", "factorize", "sgd"}, default "refine"
    loss : {"l2", "huber"}, default "l2"
        refine's loss; huber tempers outlying distances or wrong matches.
    random_state : int >= 0 or Generator, default 0
    """
    return solve(prepare(views, projections, solver, loss, random_state))


def _report(obs: Observations, rec, ids: np.ndarray, solver: str, loss: str, runtime: float) -> dict:
    from mpe3d.solvers.stress import Stress

    stress = Stress(obs)
    rms = stress.view_rms(rec.points, np.asarray(rec.projections))
    seen = obs.visibility().sum(axis=0)
    unplaced = ids[seen < 2]
    return {
        "points": int(obs.n_points), "views": int(obs.n_views),
        "setting": "fixed" if obs.fixed else "variable", "solver": solver, "loss": loss,
        "stress": float(stress.value(rec.points, np.asarray(rec.projections))),
        "stress_pairs": "sparse (k-NN and random pairs per view)" if stress.sparse else "all",
        "rms_residual_per_view": [float(r) for r in rms],
        "unplaced": {"count": int(len(unplaced)), "ids": unplaced.tolist()},
        "projections": np.asarray(rec.projections).tolist(),
        "iterations": int(rec.iterations), "termination": rec.termination,
        "runtime_s": runtime, "code": code_identity(),
    }


# -- writing -------------------------------------------------------------------

def _ply(path: Path, points: np.ndarray, ids: np.ndarray) -> None:
    """Binary PLY with an ``id`` vertex property: an int, or for text ids a list of
    UTF-8 bytes padded with NULs to one length (so readers that expect equal
    list lengths, like trimesh's, can load it)."""
    n = len(points)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if ids.dtype.kind in "iu":
        id_property, values = "property int id", [ids.astype("<i4")]
        fields.append(("id", "<i4"))
    else:
        raw = np.char.encode(ids.astype(str), "utf-8")
        width = max(1, raw.dtype.itemsize)
        id_property, values = "property list uchar uchar id", [np.full(n, width, "u1"), raw]
        fields += [("length", "u1"), ("id", f"S{width}")]
    record = np.empty(n, dtype=fields)
    for name, column in zip(record.dtype.names, [*points.T, *values]):
        record[name] = column
    header = ("ply\nformat binary_little_endian 1.0\ncomment mpe3d reconstruction\n"
              f"element vertex {n}\nproperty double x\nproperty double y\nproperty double z\n"
              f"{id_property}\nend_header\n").encode()
    with open(path, "wb") as handle:
        handle.write(header)
        handle.write(record.tobytes())


def check_output(path: str | Path, flag: str = "--out", formats=OUTPUT_FORMATS) -> Path:
    """``path`` if a file of one of ``formats`` can be written there: checked by
    creating (and removing) a file beside it, before any work is done."""
    path = Path(path)
    if path.is_dir():
        raise MpeError(f"{flag} {path}: is a folder, not a file")
    if path.suffix.lower() not in formats:
        raise MpeError(f"{flag} {path}: unknown output format '{path.suffix}' "
                       f"(expected {', '.join(formats)})")
    if path.exists() and not path.is_file():
        raise MpeError(f"{flag} {path}: not a regular file")
    if not path.parent.is_dir():
        raise MpeError(f"{flag} {path}: folder {path.parent} does not exist")
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as exc:
        raise MpeError(f"{flag} {path}: cannot write in {path.parent} "
                       f"({exc.strerror or exc})") from None
    return path


def check_ids_fit(path: Path, ids: np.ndarray) -> None:
    """PLY keeps ids as a 32-bit int or a list of at most 255 bytes: say so before solving."""
    if Path(path).suffix.lower() != ".ply" or not len(ids):
        return
    if ids.dtype.kind in "iu" and (ids.min() < -2 ** 31 or ids.max() >= 2 ** 31):
        raise MpeError(f"{path}: point ids beyond 2**31 do not fit a PLY int; "
                       "write .csv or .npy instead")
    if ids.dtype.kind not in "iu" and max(len(str(i).encode()) for i in ids) > 255:
        raise MpeError(f"{path}: point ids longer than 255 bytes do not fit a PLY list; "
                       "write .csv or .npy instead")


def _cloud_writer(path: Path, points: np.ndarray, ids: np.ndarray):
    """A function writing the cloud, by ``path``'s extension, to the file it is given."""
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return lambda temp: _ply(temp, points, ids)
    if suffix == ".csv":
        import pandas as pd

        frame = pd.DataFrame({"id": ids, "x": points[:, 0], "y": points[:, 1], "z": points[:, 2]})
        return lambda temp: frame.to_csv(temp, index=False, float_format="%.17g")
    record = np.empty(len(points), dtype=[("id", ids.dtype), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    record["id"], record["x"], record["y"], record["z"] = ids, *points.T

    def save(temp):
        with open(temp, "wb") as handle:  # np.save(path) would append .npy to the temp name
            np.save(handle, record)
    return save


def write_cloud(path: str | Path, points: np.ndarray, ids: np.ndarray) -> Path:
    """The cloud as PLY, CSV or NPY (by extension), ids kept, written atomically."""
    path = check_output(path)
    check_ids_fit(path, ids)
    atomic_write(path, _cloud_writer(path, points, ids))
    return path


def write_result(out: Path, result: Result, report: Path | None = None, extra: dict | None = None) -> None:
    """The cloud and, if asked, its JSON report: both, or neither."""
    files = [(out, _cloud_writer(out, result.points, result.ids))]
    if report is not None:
        text = json.dumps({**(extra or {}), **result.report}, indent=1)
        files.append((report, lambda temp: Path(temp).write_text(text)))
    write_together(files)
