"""Bundler v0.3 ``.out`` and BAL problem files: the bundle-adjustment world's formats.

Both hold cameras with a focal length f and radial distortion k1, k2 per view,
the 3D points, and each point's observations, and both use Bundler's
conventions: a point x is seen at P = R x + t, projected to p = -P / P_z (the
camera looks down -z), distorted to f (1 + k1 |p|^2 + k2 |p|^4) p, with the
pixel origin at the image centre and y up.

mpe3d's pinholes look down +z with y down, so reading flips y and z:
R' = F R, t' = F t and (x, y) -> (x, -y) with F = diag(1, -1, -1), a rotation,
which gives the same images (the distortion depends on |p| only). The views
come back as ``{name, ids, xy}`` dicts like every other format, plus each
view's ``start_camera`` and ``start_points`` (the file's values, in mpe3d's
conventions) for a solve that starts from them.

* Bundler ``.out`` (Snavely's Bundler, v0.3): a ``# Bundle file v0.3`` line,
  ``<cameras> <points>``, per camera ``f k1 k2``, three rows of R and t, per
  point its position, its colour and its view list ``n (camera key x y)*n``.
  A camera that Bundler did not register is all zeros: it has no view.
* BAL (Bundle Adjustment in the Large): ``<cameras> <points> <observations>``,
  one ``camera point x y`` line per observation, then per camera nine numbers
  (the rotation as an angle-axis vector, t, f, k1, k2) and per point three.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.harness.files import atomic_write

BUNDLER_HEADER = "# Bundle file v0.3"
FLIP = np.diag([1.0, -1.0, -1.0])  # Bundler's camera frame <-> mpe3d's (a rotation: det +1)
_MIN_TOKEN_BYTES = 2  # a number and its separator: what a declared count needs at least


def sniff(path: Path) -> str | None:
    """"bundler", "bal" or None, from the file's first line (its content, not its name)."""
    with open(path, "rb") as handle:
        first = handle.readline(200).decode("utf-8", "replace").strip()
    if first.startswith("# Bundle file"):
        return "bundler"
    fields = first.split()
    if len(fields) == 3 and all(f.isdigit() for f in fields):
        return "bal"
    return None


def read_bundle_file(path: str | Path) -> list[dict]:
    """The views of a Bundler ``.out`` or BAL file (found by content), with the
    file's cameras and points as ``start_camera`` / ``start_points``."""
    path = Path(path)
    kind = sniff(path)
    if kind is None:
        raise MpeError(f"{path}: neither a Bundler .out file (first line '{BUNDLER_HEADER}') "
                       "nor a BAL problem (first line '<cameras> <points> <observations>')")
    return _read_bundler(path) if kind == "bundler" else _read_bal(path)


def _numbers(path: Path, text: str, what: str) -> np.ndarray:
    try:
        values = np.array(text.split(), dtype=float)
    except ValueError as exc:
        bad = str(exc).rsplit(":", 1)[-1].strip()
        raise MpeError(f"{path}: {what}: {bad} is not a number") from None
    if not np.all(np.isfinite(values)):
        raise MpeError(f"{path}: {what}: a value is not finite (nan or inf)")
    return values


def _counts(path: Path, fields: list[str], expected: int, where: str) -> list[int]:
    if len(fields) != expected or not all(f.isdigit() for f in fields):
        raise MpeError(f"{path}: {where}: expected {expected} counts, got '{' '.join(fields)}'")
    return [int(f) for f in fields]


def _guard(path: Path, tokens: int, what: str) -> None:
    """Refuse a header that declares more numbers than the file can hold,
    before anything is allocated for them."""
    size = path.stat().st_size
    if tokens * _MIN_TOKEN_BYTES > size + 1:
        raise MpeError(f"{path}: the header declares {what}, {tokens} numbers in all, but the "
                       f"file has {size} bytes: truncated, or not this format")


def _read_bal(path: Path) -> list[dict]:
    with open(path, encoding="utf-8", errors="replace") as handle:
        n_cameras, n_points, n_obs = _counts(path, handle.readline().split(), 3, "line 1")
        _guard(path, 4 * n_obs + 9 * n_cameras + 3 * n_points,
               f"{n_cameras} cameras, {n_points} points and {n_obs} observations")
        values = _numbers(path, handle.read(), "after line 1")
    expected = 4 * n_obs + 9 * n_cameras + 3 * n_points
    if values.size != expected:
        raise MpeError(f"{path}: {values.size} numbers after line 1, but {n_cameras} cameras, "
                       f"{n_points} points and {n_obs} observations need {expected}")
    obs = values[:4 * n_obs].reshape(n_obs, 4)
    cameras = values[4 * n_obs:4 * n_obs + 9 * n_cameras].reshape(n_cameras, 9)
    points = values[4 * n_obs + 9 * n_cameras:].reshape(n_points, 3)
    view, point = obs[:, 0], obs[:, 1]
    for name, index, count in (("camera", view, n_cameras), ("point", point, n_points)):
        bad = (index != np.round(index)) | (index < 0) | (index >= count)
        if bad.any():
            row = int(np.argmax(bad))
            raise MpeError(f"{path}: observation {row + 1} (line {row + 2}): {name} index "
                           f"{index[row]:g} is not one of 0..{count - 1}")
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs every command 0.3 s to import

    rotations = Rotation.from_rotvec(cameras[:, :3]).as_matrix()
    return _views(path, view.astype(np.int64), point.astype(np.int64), obs[:, 2:4], rotations,
                  cameras[:, 3:6], cameras[:, 6], cameras[:, 7:9], points)


def read_bundle_poses(path: str | Path) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Each camera's pose (R, t) in a Bundler ``.out``, in mpe3d's (COLMAP's)
    frame, whether or not a point is seen in it (a reference may hold poses
    alone); None for a camera Bundler left out (focal length 0)."""
    path = Path(path)
    cameras = _bundler_parts(path)[0]
    poses = []
    for k, camera in enumerate(cameras):
        if not camera[0] > 0:
            poses.append(None)
            continue
        R = camera[3:12].reshape(3, 3)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise MpeError(f"{path}: camera {k}: its rotation is not a rotation matrix")
        poses.append((FLIP @ R, FLIP @ camera[12:15]))
    return poses


def _read_bundler(path: Path) -> list[dict]:
    cameras, view, point, xy, points = _bundler_parts(path)
    rotations = cameras[:, 3:12].reshape(len(cameras), 3, 3)
    return _views(path, view, point, xy, rotations, cameras[:, 12:15], cameras[:, 0], cameras[:, 1:3], points)


def _bundler_parts(path: Path):
    """A Bundler file's cameras (n, 15: f, k1, k2, R, t), and its observations
    (view, point, xy) and points, checked."""
    with open(path, encoding="utf-8", errors="replace") as handle:
        handle.readline()
        n_cameras, n_points = _counts(path, handle.readline().split(), 2, "line 2")
        # a point's view list has at least its count: 3 + 3 + 1 numbers per point
        _guard(path, 15 * n_cameras + 7 * n_points, f"{n_cameras} cameras and {n_points} points")
        values = _numbers(path, handle.read(), "after line 2")
    if values.size < 15 * n_cameras:
        raise MpeError(f"{path}: {n_cameras} cameras need {15 * n_cameras} numbers, the file "
                       f"has {values.size}")
    cameras = values[:15 * n_cameras].reshape(n_cameras, 15)
    view, point, xy, points, at = [], [], [], np.empty((n_points, 3)), 15 * n_cameras
    for i in range(n_points):
        if at + 7 > values.size:
            raise MpeError(f"{path}: point {i} of {n_points}: the file ends before it")
        points[i] = values[at:at + 3]
        n = values[at + 6]
        if n != round(n) or n < 0:
            raise MpeError(f"{path}: point {i}: its view count {n:g} is not a whole number")
        n = int(n)
        if at + 7 + 4 * n > values.size:
            raise MpeError(f"{path}: point {i} of {n_points}: the file ends inside its view list")
        entries = values[at + 7:at + 7 + 4 * n].reshape(n, 4)
        view.append(entries[:, 0])
        point.append(np.full(n, i))
        xy.append(entries[:, 2:4])
        at += 7 + 4 * n
    if at != values.size:
        raise MpeError(f"{path}: {values.size - at} numbers after the last of {n_points} points")
    view = np.concatenate(view) if view else np.zeros(0)
    bad = (view != np.round(view)) | (view < 0) | (view >= n_cameras)
    if bad.any():
        j = int(np.argmax(bad))
        raise MpeError(f"{path}: an observation names camera {view[j]:g}, not one of "
                       f"0..{n_cameras - 1}")
    point = np.concatenate(point) if point else np.zeros(0)  # a file of cameras alone has none
    xy = np.concatenate(xy) if xy else np.zeros((0, 2))
    return cameras, view.astype(np.int64), point.astype(np.int64), xy.reshape(-1, 2), points


def _views(path, view, point, xy, rotations, translations, focal, distortion, points):
    """Per camera with observations: its view dict, in mpe3d's conventions."""
    views = []
    order = np.argsort(view, kind="stable")
    view, point, xy = view[order], point[order], xy[order]
    for k in np.unique(view):
        rows = slice(*np.searchsorted(view, [k, k + 1]))
        if not focal[k] > 0:
            raise MpeError(f"{path}: camera {k} has observations but focal length {focal[k]:g}")
        R = rotations[k]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise MpeError(f"{path}: camera {k}: its rotation is not a rotation matrix")
        views.append({"name": str(k), "ids": point[rows], "xy": xy[rows] * [1.0, -1.0],
                      "start_camera": {"rotation": FLIP @ R, "translation": FLIP @ translations[k],
                                       "focal": float(focal[k]),
                                       "distortion": np.array(distortion[k], dtype=float)},
                      "start_points": points[point[rows]]})
    return views


# -- writing -------------------------------------------------------------------

def bundler_cameras(rotations, translations):
    """mpe3d's rotations (K, 3, 3) and translations (K, 3) in Bundler's frame."""
    return FLIP @ np.asarray(rotations), np.asarray(translations) @ FLIP


def write_bal(path: str | Path, view, point, xy, rotations, translations, focal, distortion,
              points) -> Path:
    """A BAL problem from observations (view, point, xy in mpe3d's pixels,
    centred) and cameras and points in mpe3d's conventions, written atomically."""
    path = Path(path)
    R, t = bundler_cameras(rotations, translations)
    from scipy.spatial.transform import Rotation

    cameras = np.concatenate([Rotation.from_matrix(R).as_rotvec(), t, np.c_[focal],
                              np.asarray(distortion).reshape(len(R), 2)], axis=1)
    obs = np.c_[view, point, np.asarray(xy) * [1.0, -1.0]]

    def save(temp):
        with open(temp, "w") as out:
            out.write(f"{len(R)} {len(points)} {len(obs)}\n")
            np.savetxt(out, obs, fmt=["%d", "%d", "%.17g", "%.17g"])
            np.savetxt(out, cameras.reshape(-1, 1), fmt="%.17g")
            np.savetxt(out, np.asarray(points).reshape(-1, 1), fmt="%.17g")
    atomic_write(path, save)
    return path


def write_bundler(path: str | Path, view, point, xy, rotations, translations, focal, distortion,
                  points) -> Path:
    """A Bundler v0.3 ``.out`` file (keys are each observation's row; colour grey)."""
    path = Path(path)
    R, t = bundler_cameras(rotations, translations)
    distortion = np.asarray(distortion).reshape(len(R), 2)
    view, point, xy = np.asarray(view), np.asarray(point), np.asarray(xy) * [1.0, -1.0]

    order = np.argsort(point, kind="stable")
    starts = np.searchsorted(point[order], np.arange(len(points) + 1))

    def save(temp):
        lines = [BUNDLER_HEADER, f"{len(R)} {len(points)}"]
        for k in range(len(R)):
            lines.append(f"{focal[k]:.17g} {distortion[k, 0]:.17g} {distortion[k, 1]:.17g}")
            lines += [" ".join(f"{v:.17g}" for v in row) for row in R[k]]
            lines.append(" ".join(f"{v:.17g}" for v in t[k]))
        for i, x in enumerate(np.asarray(points)):
            rows = order[starts[i]:starts[i + 1]]
            lines += [" ".join(f"{v:.17g}" for v in x), "128 128 128",
                      " ".join([str(len(rows))] + [f"{view[r]} {r} {xy[r, 0]:.17g} {xy[r, 1]:.17g}"
                                                   for r in rows])]
        Path(temp).write_text("\n".join(lines) + "\n")
    atomic_write(path, save)
    return path


# -- a solution out ---------------------------------------------------------------

BUNDLE_OUTPUTS = (".out", ".bal")  # what --out writes in these formats, by suffix
PINHOLE_CAMERAS = ("perspective", "radial")


def check_solution_out(path: Path, problem) -> None:
    """Refuse, before the solve, a Bundler or BAL output that could not hold its
    result: those files hold pinhole cameras (f, k1, k2) and keypoints."""
    if problem.objective != "reprojection" or problem.cameras is not None:
        raise MpeError(f"--out {path}: a {path.suffix} file holds fitted pinhole cameras; "
                       "solve the keypoints by bundle adjustment (no --projections, objective "
                       "reprojection)")
    if problem.start is None and problem.camera not in PINHOLE_CAMERAS:
        raise MpeError(f"--out {path}: a {path.suffix} file holds pinhole cameras, and "
                       f"--camera {problem.camera} may fit another; give --camera perspective or radial")


def solution_arrays(problem, result) -> dict:
    """The reconstruction of ``result`` as Bundler/BAL arrays: its placed points,
    the observations that the fit kept (centred on each camera's principal
    point, as those files measure them), and each camera's R, t, f, k1, k2."""
    placed = ~np.isin(problem.ids, result.unplaced.astype(problem.ids.dtype))
    index = np.cumsum(placed) - 1  # a placed point's row in the file
    views = problem.observations.views
    view = np.concatenate([np.full(len(v.ids), k) for k, v in enumerate(views)])
    point = np.concatenate([v.ids for v in views])
    xy = np.concatenate([v.coordinates for v in views])
    kept = result.counted & placed[point]
    cams = result.cameras
    centres = np.stack([(c.P[:, :3] @ c.rotation.T)[:2, 2] for c in cams])  # K = P[:, :3] R^T
    return {"view": view[kept], "point": index[point[kept]], "xy": xy[kept] - centres[view[kept]],
            "rotations": np.stack([c.rotation for c in cams]),
            "translations": np.stack([c.translation for c in cams]),
            "focal": np.array([c.focal_px for c in cams]),
            "distortion": np.array([[c.k1 or 0.0, c.k2 or 0.0] for c in cams]),
            "points": result.points[placed]}


def solution_writer(path: Path, problem, result):
    """A function writing ``result`` as a Bundler ``.out`` or BAL file to the path it is given."""
    if result.objective != "reprojection" or any(c.focal_px is None for c in result.cameras):
        raise MpeError(f"--out {path}: the fit has no pinhole cameras to write")
    arrays = solution_arrays(problem, result)
    write = write_bal if path.suffix.lower() == ".bal" else write_bundler
    return lambda temp: write(temp, **arrays)
