"""Alignment and the paper's metrics: Chamfer (Eq. 5), EMD (Eq. 4) and ROA.

All metrics compare the reconstruction with the ground truth *after*
alignment. Distances cannot tell mirror images apart, so the rigid alignment
allows reflections (O(3), not SO(3)) and never scales.

Scales, for comparing with the paper's tables (see the README):

* ``cd``: Eq. 5 as printed, sums of squared nearest-neighbour distances in
  both directions; grows with N. ``cd_mean`` uses means instead of sums.
* ``emd``: Eq. 4, the sum of distances over the optimal bijection (exact:
  scipy's assignment for clouds of one size, POT's ``ot.emd`` otherwise);
  ``emd_mean`` is the same per point.
* ``roa``: root-mean-square distance between corresponding points after the
  rigid alignment (paper appendix).
* ``cd_x100`` and ``emd_x100``: 100 x mean (unsquared) distances, the scale
  the authors' public code reports and most likely the one of the tables.

Camera poses are scored as structure from motion is (:func:`relative_pose_errors`,
:func:`pose_auc`): COLMAP's own benchmark, the relative-pose AUC.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

RANSAC_TRIALS = 1000


def rigid_transform(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Q, t) minimising sum ||target_i - (Q source_i + t)||^2 over Q in O(3)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    H = (source - mu_s).T @ (target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    Q = (U @ Vt).T  # no det correction: reflections are allowed
    return Q, mu_t - Q @ mu_s


def align_rigid(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``source`` moved onto ``target`` by the best O(3) motion (no scaling)."""
    Q, t = rigid_transform(source, target)
    return source @ Q.T + t


def align_ransac4(source: np.ndarray, target: np.ndarray, rng: np.random.Generator,
                  trials: int = RANSAC_TRIALS) -> np.ndarray:
    """Paper Eq. 6-8: the affine map T = A X^-1 through 4 random correspondences,
    best of ``trials`` by the mean distance over all points."""
    N = len(source)
    hs = np.hstack([source, np.ones((N, 1))])
    ht = np.hstack([target, np.ones((N, 1))])
    best, best_loss = hs[:, :3], np.inf
    picks = np.stack([rng.choice(N, size=4, replace=False) for _ in range(trials)])
    Xh = np.swapaxes(hs[picks], 1, 2)  # (trials, 4, 4), points as columns
    Ah = np.swapaxes(ht[picks], 1, 2)
    ok = np.abs(np.linalg.det(Xh)) > 1e-12
    T = np.swapaxes(np.linalg.solve(np.swapaxes(Xh[ok], 1, 2), np.swapaxes(Ah[ok], 1, 2)), 1, 2)
    for chunk in np.array_split(T, max(1, len(T) // 64)):
        moved = np.einsum("tij,nj->tni", chunk[:, :3, :], hs)
        loss = np.linalg.norm(moved - target[None], axis=2).mean(axis=1)
        i = int(np.argmin(loss))
        if loss[i] < best_loss:
            best, best_loss = moved[i], float(loss[i])
    return best


def chamfer(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Eq. 5 (sums of squared NN distances), its mean form, and the x100 scale."""
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return {
        "cd": float(np.sum(d_ab ** 2) + np.sum(d_ba ** 2)),
        "cd_mean": float(np.mean(d_ab ** 2) + np.mean(d_ba ** 2)),
        "cd_x100": float(100.0 * (np.mean(d_ab) + np.mean(d_ba))),
    }


def earth_movers(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Eq. 4: sum of distances over the optimal bijection (exact transport).

    Two clouds of one size with equal masses: the optimal transport plan is a
    permutation (Birkhoff), so the exact EMD is the assignment problem, which
    scipy solves (``linear_sum_assignment``: the same optimum as POT's network
    simplex, 10x faster at 2,048 points, and no import of POT, which brings
    scikit-learn into every fresh process). Clouds of different sizes
    (COLMAP's points against surface samples) are matched by POT's optimal
    transport of equal masses 1/len per point; the sum form then counts
    len(a) points, so both forms agree with Eq. 4 whenever the sizes are equal.
    """
    n, m = len(a), len(b)
    M = cdist(a, b)
    if n == m:
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(M)
        mean = float(np.mean(M[rows, cols]))
    else:
        import ot  # here, not at the top: POT imports scikit-learn, a second of a fresh process

        plan = ot.emd(np.full(n, 1.0 / n), np.full(m, 1.0 / m), M, numItermax=max(100_000, 50 * n * m))
        mean = float(np.sum(plan * M))
    return {"emd": n * mean, "emd_mean": mean, "emd_x100": 100.0 * mean}


def similarity_transform(source: np.ndarray, target: np.ndarray, mirror: bool = False):
    """(s, Q, t) minimising sum ||target_i - (s Q source_i + t)||^2 (Umeyama), Q a
    rotation, or any orthogonal matrix with ``mirror``."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.ones(3)
    if not mirror and np.linalg.det(U @ Vt) < 0:
        d[2] = -1.0
    Q = (U * d) @ Vt
    s = float(np.sum(S * d) / np.sum(a ** 2))
    return s, Q, mu_t - s * Q @ mu_s


def robust_similarity(source: np.ndarray, target: np.ndarray, rng: np.random.Generator,
                      mirror: bool = False, trials: int = RANSAC_TRIALS // 5):
    """:func:`similarity_transform` that a minority of wild pairs cannot bend:
    least median of squares over ``trials`` fits to 3 random pairs, then the
    least-squares fit to the pairs within 3 robust sigmas of it, twice."""
    n = len(source)
    if n <= 3:
        return similarity_transform(source, target, mirror)

    def misfit(fit):
        s, Q, t = fit
        return np.linalg.norm(s * source @ Q.T + t - target, axis=1)

    best, best_median = None, np.inf
    for _ in range(trials):
        pick = rng.choice(n, 3, replace=False)
        fit = similarity_transform(source[pick], target[pick], mirror)
        median = float(np.median(misfit(fit)))
        if np.isfinite(median) and median < best_median:
            best, best_median = fit, median
    if best is None:
        return similarity_transform(source, target, mirror)
    for _ in range(2):
        r = misfit(best)
        inliers = r <= 3.0 * 1.4826 * max(np.median(r), 1e-300)
        if np.count_nonzero(inliers) < 3:
            break
        best = similarity_transform(source[inliers], target[inliers], mirror)
    return best


def roa(source: np.ndarray, target: np.ndarray) -> float:
    """RMSE over corresponding points after the rigid O(3) alignment."""
    moved = align_rigid(source, target)
    return float(np.sqrt(np.mean(np.sum((moved - target) ** 2, axis=1))))


def evaluate(truth: np.ndarray, reconstruction: np.ndarray, align: str = "rigid",
             random_state=None) -> tuple[dict[str, float], np.ndarray]:
    """All metrics of ``reconstruction`` against ``truth``, and the aligned cloud."""
    if align == "ransac4":
        aligned = align_ransac4(reconstruction, truth, np.random.default_rng(random_state))
    else:
        aligned = align_rigid(reconstruction, truth)
    metrics = {**chamfer(aligned, truth), **earth_movers(aligned, truth),
               "roa": roa(reconstruction, truth)}
    return metrics, aligned


POSE_AUC_THRESHOLDS = (0.5, 1.0, 3.0, 5.0, 10.0)  # degrees: COLMAP's benchmark's, and AUC@3 (the IMC's)


def relative_pose_errors(estimated: dict, reference: dict) -> np.ndarray:
    """The relative pose error of every ordered pair of the ``reference``'s
    photos, in degrees, as COLMAP's benchmark defines it
    (``benchmark/reconstruction/evaluation/utils.py``,
    ``compute_grouped_rel_errors`` with one model and one reference component):
    the larger of the angle of R_est^T R_ref, the two relative rotations, and
    the angle between the two relative translations' directions; 180 for a
    pair not registered together. Both are ``{name: (R, t)}`` of
    ``x_cam = R x + t``; a photo missing from ``estimated`` (or whose R is
    not finite) was not registered, and estimated photos the reference does
    not have are left out."""
    names = sorted(reference)
    errors = []
    for src in names:
        for tgt in names:
            if src == tgt:
                continue
            if not all(n in estimated and np.all(np.isfinite(estimated[n][0])) for n in (src, tgt)):
                errors.append(180.0)
                continue
            (R_est, t_est), (R_ref, t_ref) = (_relative(poses[src], poses[tgt])
                                              for poses in (estimated, reference))
            cos_r = (np.trace(R_est.T @ R_ref) - 1.0) / 2.0
            d_r = np.degrees(np.arccos(np.clip(cos_r, -1.0, 1.0)))
            cos_t = np.dot(t_est, t_ref) / max(np.linalg.norm(t_est) * np.linalg.norm(t_ref), 1e-300)
            d_t = np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0)))
            errors.append(float(max(d_r, d_t)))
    return np.array(errors)


def _relative(src, tgt):
    """tgt_from_src of two cam_from_world poses (R, t)."""
    (R_s, t_s), (R_t, t_t) = src, tgt
    R = np.asarray(R_t) @ np.asarray(R_s).T
    return R, np.asarray(t_t) - R @ np.asarray(t_s)


def pose_auc(errors: np.ndarray, thresholds=POSE_AUC_THRESHOLDS) -> np.ndarray:
    """The area under the recall curve of ``errors`` up to each threshold, in
    per cent of the threshold: COLMAP's ``compute_auc`` (trapezoid rule over
    the sorted errors, from recall 0 at error 0)."""
    errors = np.sort(np.asarray(errors, dtype=float))
    if not len(errors):
        raise ValueError("no pose errors to score")
    recalls = np.r_[0.0, (np.arange(len(errors)) + 1) / len(errors)]
    errors = np.r_[0.0, errors]
    aucs = []
    for t in thresholds:
        last = np.searchsorted(errors, t, side="right")
        r = np.r_[recalls[:last], recalls[last - 1]]
        e = np.r_[errors[:last], t]
        aucs.append(100.0 * np.trapezoid(r, x=e) / t)
    return np.array(aucs)
