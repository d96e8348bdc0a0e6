"""Wrong matches out, and back in where the fit explains them: rounds of
dropping observations beyond OUTLIER_THRESHOLD robust sigmas, points that ran
away dropped and solved again, and readmission of what a suspicion or an
early drop took out."""

from __future__ import annotations

import numpy as np

from mpe3d.options import OUTLIER_THRESHOLD
from mpe3d.solvers.sfm.adjust import LMOptions, adjust
from mpe3d.solvers.sfm.support import FAR_FACTOR, informative, median_radii, placed_points, weak_points
from mpe3d.solvers.sfm.tracks import residual_lengths, robust_sigma, sigma_of
from mpe3d.solvers.sfm.triangulation import (
    adjusted_points,
    robust_points,
)

# rounds of peeling: the first take the gross wrong matches, the later ones a
# handful each as the sigma shrinks, which the readmission judges again anyway
# (250 photos: 20 rounds of 1-25 drops, 9 s; 8 rounds, the same 1,318 dropped
# in the end; VGG's tracks with 3 % wrong matches: the same drops)
_OUTLIER_ROUNDS = 8
_READMISSION_ROUNDS = 4
PER_VIEW = 0.005  # of a view's observations peeled in one round, at most (one at least)
_RUNAWAY_ROUNDS = 3  # solves without the points that ran away


def without_runaways(fit, tracks, used, lm: LMOptions):
    """A solve that did not converge because points ran away (a wrong match
    along its epipolar line, in a track of two views, puts its point at a
    depth the pinhole chases towards infinity, and the shared damping holds
    back every other parameter): solved again without the points beyond
    ``FAR_FACTOR`` median radii, until none is left. Returns the fit and the
    observations of the points left out, for the caller's suspects."""
    out = np.zeros(len(tracks.view), dtype=bool)
    for _ in range(_RUNAWAY_ROUNDS):
        if fit.converged:
            break
        placed = placed_points(tracks, used & ~out)
        far = placed & ~(median_radii(fit.X, placed) <= FAR_FACTOR)
        if not far.any() or far.sum() > placed.sum() / 2:
            break
        out |= far[tracks.point] & used
        again = adjust(fit.X, fit.cameras, tracks.subset(informative(tracks, used & ~out)), lm)
        fit = again._replace(history=np.concatenate([fit.history, again.history[1:]]))
    return fit, out


def _readmitted(fit, tracks, dropped, threshold, lm: LMOptions, seed: int = 0):
    """The fit after every point with dropped observations is triangulated again,
    robustly, under its cameras (:func:`.triangulation.robust_points`), and
    solved again with the observations it explains (within ``threshold``
    robust sigmas) taken back and those it does not dropped, until that
    changes nothing: a suspicion raised before the fit, or a drop made while a
    wrong match still dragged its point, is not the final word. Returns the
    fit, the observations dropped, and whether anything changed (and the fit
    was solved to the end)."""
    if not np.isfinite(threshold):
        return fit, dropped, False
    # the rounds solve loosely (a real set of 11 photos and 50,000 observations:
    # 4 rounds to the end took 38 s), the last one to the end
    loose = lm.round()
    changed = False
    for _ in range(_READMISSION_ROUNDS):
        X, cameras = fit[:2]
        tau = threshold * robust_sigma(X, cameras, tracks, informative(tracks, ~dropped))
        suspects = np.unique(tracks.point[dropped])
        X, outlying = robust_points(X, cameras, tracks, suspects, tau, seed)
        again = np.where(np.isin(tracks.point, suspects), outlying, dropped)
        if (again == dropped).all():
            break
        changed = True
        fit = adjust(X, cameras, tracks.subset(informative(tracks, ~again)), loose)
        fit, after = without_outliers(fit, tracks, again, threshold, loose)
        cycled = (after == dropped).all()
        dropped = after
        if cycled:
            # what it took back the fit dropped again: each further round would
            # too (11 photos of 3,000 px through a lens: 1,823 <-> 1,828, three
            # rounds of 1.2 s each)
            break
    if changed:
        fit = adjust(*fit[:2], tracks.subset(informative(tracks, ~dropped)), lm)
    return fit, dropped, changed


def finite_threshold(threshold):
    return threshold if np.isfinite(threshold) else OUTLIER_THRESHOLD


def peel_outliers(fit, tracks, flagged, threshold, lm: LMOptions, seed: int = 0, solved: bool = True):
    """The fit and the observations dropped after wrong matches are peeled off
    (:func:`without_outliers`) and what the fit explains is taken back
    (:func:`_readmitted`), with the points of weak geometry under ``fit`` set
    aside: :func:`_without_weak` leaves them out of the last solve anyway,
    and their depth, which the views barely fix, is what every solve with
    them spends its last iterations on (COLMAP's tracks of 250 photos: 14
    such points; the peeling's 21 solves took 156 iterations with them, 21
    without). They are then adjusted alone under the cameras found
    (:func:`.triangulation.adjusted_points`), as the solves would have
    placed them. Their observations flagged before stay dropped. A fit not
    ``solved`` to ``lm``'s tolerance (a start solved loosely) is solved to it
    when no round did."""
    weak = weak_points(fit, tracks, ~flagged)[0]
    rows = ~weak[tracks.point]
    strong = tracks.subset(rows)
    # the peeling's last solve is loose too: the readmission's (or the one
    # below) finishes it (11 photos, 79,000 observations: 19 iterations, 2.3 s)
    fit, peeled = without_outliers(fit, strong, flagged[rows], threshold, lm, finish=False)
    solved = solved and not (peeled != flagged[rows]).any()
    fit, peeled, changed = _readmitted(fit, strong, peeled, threshold, lm, seed)
    if not (solved or changed):
        fit = adjust(*fit[:2], strong.subset(informative(strong, ~peeled)), lm)
    dropped = flagged.copy()
    dropped[rows] = peeled
    if weak.any():
        fit = fit._replace(X=adjusted_points(fit.X, fit.cameras, tracks.subset(~dropped), weak))
    return fit, dropped


def without_outliers(fit, tracks, dropped, threshold, lm: LMOptions, finish: bool = True):
    """Find wrong matches, drop them and solve again, until none is left.

    Peeling: the observations beyond ``threshold`` robust sigmas (from the
    median residual length) are dropped, at most one per point and one per
    view and round, the worst (a wrong match drags its point and its camera,
    and so their other residuals, with it), and only where the point keeps 3
    views, so that it stays placed and testable. As the fit sheds them the
    sigma shrinks and subtler ones show. A view keeps at least 6 observations.
    The rounds solve loosely; the last one to the end when ``finish``.
    """
    if not np.isfinite(threshold):
        return fit, dropped
    before = dropped
    for _ in range(_OUTLIER_ROUNDS):
        kept = informative(tracks, ~dropped)
        X, cameras = fit[:2]
        raw = residual_lengths(X, cameras, tracks)
        sigma = sigma_of(raw[kept], tracks)
        length = np.where(kept, np.nan_to_num(raw, nan=np.inf), -1.0)
        if not (length > threshold * sigma).any():  # none beyond: nothing to rank
            break
        ranked = np.argsort(length)
        worst = np.intersect1d(_last_of(tracks.point[ranked], ranked),  # the worst of its point
                               _worst_of_views(tracks.view[ranked], ranked, kept, tracks))  # and of its view
        counts = np.bincount(tracks.point[kept], minlength=tracks.n_points)
        worst = worst[(length[worst] > threshold * sigma) & (counts[tracks.point[worst]] >= 4)]
        bad = np.zeros(len(tracks.view), dtype=bool)
        bad[worst] = True
        room = np.bincount(tracks.view[~dropped & ~bad], minlength=tracks.n_views) >= 6
        bad &= room[tracks.view]
        if not bad.any():
            break
        dropped = dropped | bad
        fit = adjust(X, cameras, tracks.subset(informative(tracks, ~dropped)), lm.round())
    if finish and (dropped != before).any():  # the rounds solve loosely: the last one to the end
        fit = adjust(*fit[:2], tracks.subset(informative(tracks, ~dropped)), lm)
    return fit, dropped


def _worst_of_views(views: np.ndarray, ranked: np.ndarray, kept: np.ndarray, tracks) -> np.ndarray:
    """The last (worst) ``PER_VIEW`` share of each view's ``kept``
    observations in the order ``ranked``, one at least: a wrong match drags
    its camera by about 1 / (the view's observations), so a view with
    hundreds of them can shed several a round (11 photos of 3,000 px, 2,000
    wrong matches: 20 rounds of 11 drops each, 19 s, peeled a tenth of them)."""
    counts = np.bincount(tracks.view[kept], minlength=tracks.n_views)
    allowed = np.maximum(1, (PER_VIEW * counts).astype(int))
    order = np.argsort(views[::-1], kind="stable")  # each view's items, worst first
    grouped = views[::-1][order]
    starts = np.searchsorted(grouped, np.arange(tracks.n_views))
    rank = np.arange(len(order)) - starts[grouped]
    return np.sort(ranked[::-1][order][rank < allowed[grouped]])


def _last_of(groups: np.ndarray, items: np.ndarray) -> np.ndarray:
    """The last item of each group, in the order given."""
    _, first = np.unique(groups[::-1], return_index=True)
    return np.sort(items[::-1][first])

