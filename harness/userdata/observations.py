"""A user's views as :class:`mpe3d.solvers.Observations`: "not seen" markers
dropped, distance matrices checked (square, symmetric, finite, zero on the
diagonal), and the points' labels (ints or strings) mapped to indices, every
error one line naming the file, view and row."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.harness.userdata.formats import finite_array
from mpe3d.solvers import Observations, View
from mpe3d.solvers.degenerate import MIN_VIEW_POINTS

LIKELY_MISSING = ((-1.0, -1.0), (0.0, 0.0))  # what OpenCV and VGG files write for "not seen"
SYMMETRY_TOL = 1e-6  # relative: distance matrices written as text lose a little


def drop_missing(views: Sequence[dict], missing=None, source: str = "input"):
    """The views without the observations at exactly ``missing`` (x, y), and a
    note per view where observations sit exactly at (-1, -1) or (0, 0), the
    marks that tracking files use for "not seen" (when ``missing`` is None)."""
    notes, out = [], []
    for k, view in enumerate(views):
        if "xy" not in view:
            out.append(view)
            continue
        xy = np.asarray(view["xy"])
        name = view.get("name", k)
        if xy.ndim != 2 or xy.shape != (len(view["ids"]), 2) or xy.dtype.kind not in "iuf":
            out.append(view)  # observations_from says what is wrong with it
            continue
        if missing is not None:
            keep = ~np.all(xy == np.asarray(missing, dtype=float), axis=1)
            kept = {key: np.asarray(view[key])[keep] for key in ("ids", "xy", "start_points")
                    if key in view}
            out.append({**view, **kept})
            continue
        out.append(view)
        for mark in LIKELY_MISSING:
            hit = np.all(xy == mark, axis=1)
            # (0, 0) is a pixel like any other, unless two points of one view sit on it
            if np.count_nonzero(hit) > (1 if mark == (0.0, 0.0) else 0):
                ids = np.asarray(view["ids"])[hit]
                shown = ", ".join(map(str, ids[:10])) + (f", ... ({len(ids)} in all)"
                                                         if len(ids) > 10 else "")
                x, y = (int(v) for v in mark)
                notes.append(f"{source}: view '{name}': {len(ids)} observations at exactly "
                             f"({x}, {y}), likely missing markers (ids {shown}); "
                             f"missing=({x}, {y}) (--missing={x},{y}) drops them")
    return out, notes


# -- checking ------------------------------------------------------------------

def _check_dist(D: np.ndarray, n: int, where: str) -> np.ndarray:
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise MpeError(f"{where}: dist is {'x'.join(map(str, D.shape))}, not square")
    if D.shape[0] != n:
        raise MpeError(f"{where}: dist is {D.shape[0]}x{D.shape[0]} but ids has {n} entries; "
                       "they must match")
    D = finite_array(D, where, "dist")
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
        if len(ids) < MIN_VIEW_POINTS:
            raise MpeError(f"{where} has {len(ids)} point(s); each view needs at least {MIN_VIEW_POINTS}")
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
            xy = finite_array(view["xy"], where, "xy")
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

