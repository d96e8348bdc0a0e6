"""The file formats of ``mpe3d reconstruct``: views in, clouds out.

Inputs (checked hard at this boundary, every error one line naming the file,
view and row):

* CSV, long format with a header ``view,point,x,y``: one row per observation;
* NPZ with ``view<k>_ids`` and ``view<k>_xy`` or ``view<k>_dist`` arrays, or
  a folder with one ``<name>.npz`` per view holding ``ids`` and ``xy`` or
  ``dist``;
* JSON ``{"views": [{"ids": [...], "xy": [[x, y], ...]} | {"ids": [...], "dist": [[...]]}]}``;
* a COLMAP sparse model folder (``cameras``, ``images``, ``points3D``, binary
  or text): its tracks as keypoints (:func:`mpe3d.harness.userdata.colmap_model.read_model`);
* a Bundler ``.out`` or BAL problem file, known by content
  (:mod:`mpe3d.harness.userdata.bundler`), with its cameras and points as a start.

Known cameras (the fixed setting) come as a ``.npy`` or ``.json`` of K
matrices: 2x3 with orthonormal rows or 3x3 rotations (orthographic), or 3x4
pinhole camera matrices. Clouds go out as PLY, CSV or NPY with their ids,
written atomically.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError, first_line
from mpe3d.harness.files import atomic_write, write_together
from mpe3d.options import DEFAULT_MATCHES

OUTPUT_FORMATS = (".ply", ".csv", ".npy")
ORTHONORMAL_TOL = 1e-6

# -- reading -------------------------------------------------------------------

def finite_array(values: np.ndarray, where: str, what: str) -> np.ndarray:
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


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Reference 3D points from a CSV file ``id,x,y,z``: their ids (as text, to
    match any input's) and an (N, 3) array."""
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise MpeError(f"{path}: no such file")
    try:
        _check_header(path)
        frame = pd.read_csv(path, dtype={"id": str}, keep_default_na=False)
    except pd.errors.EmptyDataError:
        raise MpeError(f"{path}: empty file") from None
    except (pd.errors.ParserError, UnicodeDecodeError, csv.Error) as exc:
        raise MpeError(f"{path}: not a UTF-8 CSV file ({first_line(exc)})") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    missing = [c for c in ("id", "x", "y", "z") if c not in frame.columns]
    if missing or frame.empty:
        raise MpeError(f"{path}: expected a header id,x,y,z and one row per point")
    xyz = frame[["x", "y", "z"]].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(~np.isfinite(xyz).all(axis=1))
    if len(bad):
        raise MpeError(f"{path}: row {int(bad[0]) + 2}: x, y and z must be finite numbers")
    ids = frame["id"].astype(str).str.strip().to_numpy()
    if len(set(ids)) < len(ids):
        raise MpeError(f"{path}: a point id appears twice")
    return ids, xyz


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
        raise MpeError(f"{path}: a folder input needs photos (.jpg, .png, ...), a COLMAP model "
                       "(cameras, images, points3D) or one .npz file per view (ids, and xy or dist)")
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


_DIGESTS: dict = {}


def content_digest(path: str | Path) -> str:
    """``sha256:<hex>`` of a file's bytes, or of a folder's files (their relative
    names and bytes, in sorted order): what identifies a data set, wherever it lies.
    Remembered per (path, size, modification time), so asking again costs a stat."""
    path = Path(path)
    if not path.exists():
        raise MpeError(f"{path}: no such file or folder")
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    if path.is_file() and path.suffix.lower() not in (".csv", ".npz", ".json", ".npy"):
        from mpe3d.harness.userdata import vgg

        if vgg.sniff(path):  # its corners, cameras and points are part of the data set
            files += vgg.companions(path)
    stamp = (str(path.resolve()), tuple((str(p), p.stat().st_size, p.stat().st_mtime_ns) for p in files))
    if stamp not in _DIGESTS:
        digest = hashlib.sha256()
        for file in files:
            if file != path:
                base = path if path.is_dir() else path.parent
                digest.update(f"{Path(os.path.relpath(file, base)).as_posix()}\n".encode())
            with open(file, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
        _DIGESTS[stamp] = f"sha256:{digest.hexdigest()}"
    return _DIGESTS[stamp]


def is_photo_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder that :func:`read_views` reads as photos
    (not a COLMAP model, no ``.npz`` views beside them)."""
    path = Path(path)
    if not path.is_dir():
        return False
    from mpe3d.harness.userdata import photo_folder
    from mpe3d.harness.userdata.colmap_model import looks_like_model

    # raw camera files alone are photos too: the photo reader says in one line what to do with them
    return not looks_like_model(path) and not any(path.glob("*.npz")) and bool(
        photo_folder.list_photos(path) or photo_folder.raw_photos(path))


def read_views(path: str | Path, matches: str = DEFAULT_MATCHES, *, seed: int = 0,
               scratch: str | Path | None = None) -> list[dict]:
    """The views of an input file as dicts ``{name, ids, xy | dist}``, not yet checked;
    a folder of photos or a COLMAP database gives its tracks of ``matches``
    (photos: COLMAP's database under ``scratch``, its RANSAC seeded by ``seed``)."""
    path = Path(path)
    if path.is_dir():
        from mpe3d.harness.userdata import photos
        from mpe3d.harness.userdata.colmap_model import looks_like_model, read_model

        if looks_like_model(path):
            return read_model(path)
        if is_photo_folder(path):
            return photos.read_photos(path, matches, seed=seed, scratch=scratch)
        return _read_folder(path)
    if not path.exists():
        raise MpeError(f"{path}: no such file")
    if not path.is_file():
        raise MpeError(f"{path}: not a regular file")
    readers = {".csv": _read_csv, ".npz": _read_npz, ".json": _read_json}
    reader = readers.get(path.suffix.lower())
    if path.stat().st_size == 0:
        raise MpeError(f"{path}: empty file")
    if reader is None:
        from mpe3d.harness.userdata import bundler, photos, vgg

        if photos.looks_like_database(path):
            return photos.read_database(path, matches)

        if vgg.sniff(path):  # before BAL: a 3-view table's first row is 3 integers too
            return vgg.read_nview(path)
        if bundler.sniff(path) is None:  # Bundler and BAL files are known by content, any name
            raise MpeError(f"{path}: unknown input format '{path.suffix}' (expected .csv, .npz, "
                           ".json, a folder of .npz files or photos, a COLMAP model folder or "
                           "database, a Bundler .out, a BAL problem or a VGG nview-corners file)")
        return bundler.read_bundle_file(path)
    return reader(path)


def read_projections(path: str | Path) -> np.ndarray:
    """Known cameras from a .npy or .json file: ``(K, 2, 3)`` orthographic rows
    (from 2x3 matrices with orthonormal rows or 3x3 rotations), or ``(K, 3, 4)``
    pinhole camera matrices, all K of one kind."""
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
        m = finite_array(m, f"{path}: projection {k}", "matrix")
        if m.shape not in ((2, 3), (3, 3), (3, 4)):
            raise MpeError(f"{path}: projection {k} is {'x'.join(map(str, m.shape))}, "
                           "expected 2x3 (orthonormal rows), 3x3 (a rotation) or 3x4 (a pinhole camera)")
        if mats and (m.shape == (3, 4)) != (mats[0].shape == (3, 4)):
            raise MpeError(f"{path}: projection {k} is {'x'.join(map(str, m.shape))} but "
                           f"projection 0 is {'x'.join(map(str, mats[0].shape))}: give one kind")
        if m.shape == (3, 4):
            if np.linalg.matrix_rank(m[:, :3]) < 3:
                raise MpeError(f"{path}: projection {k}: its left 3x3 block is singular, "
                               "no pinhole camera")
            mats.append(m)
            continue
        error = np.abs(m @ m.T - np.eye(len(m))).max()
        if error > ORTHONORMAL_TOL:
            raise MpeError(f"{path}: projection {k}: rows are not orthonormal "
                           f"(largest |P P^T - I| entry {error:.2g})")
        mats.append(m[:2])
    return np.stack(mats)


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


def write_result(out: Path, result, report: Path | None = None, extra: dict | None = None,
                 writer=None) -> None:
    """The cloud of ``result`` (its points, ids and report; or what ``writer``
    writes) and, if asked, its JSON report: both, or neither."""
    files = [(out, writer or _cloud_writer(out, result.points, result.ids))]
    if report is not None:
        text = json.dumps({**(extra or {}), **result.report}, indent=1)
        files.append((report, lambda temp: Path(temp).write_text(text)))
    write_together(files)

