"""Input that cannot determine a shape, said clearly.

An error when no meaningful result exists (a view with fewer than 3 points,
views that share too few points to be tied together); a warning when a
result exists but part of it is not determined (points seen in fewer than 2
views, the 2-view variable-setting ambiguity).
"""

from __future__ import annotations

import contextlib
import warnings
from typing import Iterator

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.solvers.base import Observations

MIN_VIEW_POINTS = 3  # points a view must show to be placed
# Shared points that tie two views together: an O(2) transform and a shift per
# view (fixed), or an affine camera (variable, 4 points not all coplanar).
SHARED_FIXED, SHARED_VARIABLE = 3, 4


class DegenerateWarning(UserWarning):
    """The input leaves part of the reconstruction undetermined.

    ``template`` and ``ids`` keep the point ids a message names apart from its
    text, so that a caller who knows the user's ids can say those instead of
    the solver's indices (:func:`collect_notes`).
    """

    def __init__(self, template: str, ids=None):
        self.template, self.ids = template, ids
        super().__init__(template.format(ids=_ids(np.asarray(ids))) if ids is not None else template)

    def text(self, labels=None) -> str:
        if self.ids is None or labels is None:
            return str(self)
        return self.template.format(ids=_ids(np.asarray(labels)[np.asarray(self.ids)]))


def warn(message: str, ids=None) -> None:
    """Warn about the input; a message naming points says ``{ids}`` and passes them."""
    warnings.warn(DegenerateWarning(message, ids), stacklevel=3)


@contextlib.contextmanager
def collect_notes(labels=None) -> Iterator[list[str]]:
    """Collect the :class:`DegenerateWarning` messages raised inside the block
    (notes about the input, which travel with the result) into the yielded
    list, filled when the block ends, naming points by ``labels[index]`` when
    given; other warnings go on as usual."""
    notes: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DegenerateWarning)
        yield notes
    for w in caught:
        if issubclass(w.category, DegenerateWarning):
            notes.append(w.message.text(labels) if isinstance(w.message, DegenerateWarning)
                         else str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _ids(values: np.ndarray, limit: int = 10) -> str:
    shown = ", ".join(map(str, values[:limit]))
    return shown + (f", ... ({len(values)} in all)" if len(values) > limit else "")


def view_groups(shared: np.ndarray, need: int) -> tuple[int, np.ndarray]:
    """The groups of views tied together by chains of pairs sharing ``need``
    points or more (``shared``: K x K counts): their number and each view's label."""
    from scipy.sparse import csr_matrix  # here: scipy.sparse and csgraph cost 0.23 s of a process's imports
    from scipy.sparse.csgraph import connected_components

    return connected_components(csr_matrix(shared >= need), directed=False)


def shared_points(view: np.ndarray, point: np.ndarray, n_views: int, n_points: int) -> np.ndarray:
    """(K, K) int64: how many points each pair of views shows, from each
    observation's ``view`` and ``point`` (each pair at most once); a sparse
    product, since a dense views x points matrix is mostly zeros (100 photos x
    50,000 tracks: 45 times faster)."""
    from scipy.sparse import csr_matrix

    seen = csr_matrix((np.ones(len(view), dtype=np.int64), (np.asarray(view, dtype=np.int64),
                                                            np.asarray(point, dtype=np.int64))),
                      shape=(n_views, n_points))
    return np.asarray((seen @ seen.T).toarray(), dtype=np.int64)


def check_geometry(obs: Observations) -> np.ndarray:
    """Raise or warn on degenerate input; return the ids seen in fewer than 2 views."""
    small = [k for k, view in enumerate(obs.views) if view.size < MIN_VIEW_POINTS]
    if small:
        raise MpeError(f"views {small} show fewer than {MIN_VIEW_POINTS} points: a view needs "
                       f"{MIN_VIEW_POINTS} to be placed")
    view = np.concatenate([np.full(v.size, k, dtype=np.int64) for k, v in enumerate(obs.views)])
    point = np.concatenate([np.asarray(v.ids, dtype=np.int64) for v in obs.views])
    shared = shared_points(view, point, obs.n_views, obs.n_points)
    need = SHARED_FIXED if obs.fixed else SHARED_VARIABLE
    count, labels = view_groups(shared, need)
    if count > 1:
        groups = [np.flatnonzero(labels == c).tolist() for c in range(count)]
        across = max(int(shared[i, j]) for i in range(obs.n_views) for j in range(obs.n_views)
                     if labels[i] != labels[j])
        raise MpeError(f"views {' and '.join(map(str, groups))} share too few points to be tied "
                       f"together (at most {across} in common, {need} needed)")
    if not obs.fixed and obs.n_views == 2:
        warn("2 views with variable projections leave the depth ambiguous (a known "
             "ambiguity of two affine views): the shape is not determined")
    unplaced = np.flatnonzero(np.bincount(point, minlength=obs.n_points) < 2)
    if len(unplaced):
        warn(f"{len(unplaced)} points are seen in fewer than 2 views and cannot be placed: "
             "ids {ids}", ids=unplaced)
    return unplaced
