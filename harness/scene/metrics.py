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
:func:`pose_auc`): COLMAP's own benchmark, the relative-pose AUC; :func:`score_poses`
adds the photos registered and the camera-centre error after a similarity.
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


POSE_AUC_THRESHOLDS = (1, 3, 5, 10)  # degrees: AUC@3/5/10 as the IMC and learned SfM report it, and @1
COLMAP_EPS = 1e-10  # COLMAP's normalize_vec: a vector is divided by max(eps, its norm)


def relative_pose_errors(reference: dict, estimated: dict) -> np.ndarray:
    """The relative pose errors, in degrees, of COLMAP's benchmark.

    Follows ``benchmark/reconstruction/evaluation/utils.py`` of COLMAP
    (``compute_grouped_rel_errors`` with one estimated model and one
    reference component, ``compute_rel_pose_error`` with
    ``min_proj_center_dist`` 0, and ``geometry.py``'s ``vec_angular_dist_deg``).
    Both arguments are ``{photo name: (R, t)}`` of ``x_cam = R x + t``; an
    estimated photo whose R is not finite counts as not registered.

    For an ordered pair (i, j) of photos, ``R_ij = R_j R_i^T`` and
    ``t_ij = t_j - R_ij t_i`` (camera j from camera i). For every ordered pair
    that both the reference and the estimate hold, the error is
    ``max(angle(R_ij,est^T R_ij,ref), angle(t_ij,est, t_ij,ref))``, where a
    translation is divided by ``max(1e-10, |t|)`` before the angle, so a zero
    relative translation (two photos from one place) scores 90 degrees. Every
    ordered pair that only one of them holds scores 180: a photo the estimate
    did not register, and also (as COLMAP's code has it, beyond the usual
    summary) each pair of registered photos of which one is not posed in the
    reference ("a registered outlier"). No pair at all gives ``[180]``.
    The measured pairs come first, in name order, then the 180s.
    """
    posed = {n for n, (R, _) in estimated.items() if np.all(np.isfinite(np.asarray(R, dtype=float)))}
    both = sorted(posed & set(reference))
    n_ref, n_est, m = len(reference), len(posed), len(both)
    unmatched = n_ref * (n_ref - 1) + n_est * (n_est - 1) - 2 * m * (m - 1)  # the symmetric difference
    measured = _pair_errors([reference[n] for n in both], [estimated[n] for n in both])
    errors = np.concatenate([measured, np.full(unmatched, 180.0)])
    return errors if len(errors) else np.array([180.0])


def _pair_errors(reference: list, estimated: list) -> np.ndarray:
    """max(rotation error, translation direction error) of every ordered pair."""
    if len(reference) < 2:
        return np.zeros(0)
    R_ref, t_ref = _relative_poses(reference)
    R_est, t_est = _relative_poses(estimated)
    d_R = _rotation_angle(np.einsum("...ba,...bc->...ac", R_est, R_ref))  # estimated_from_gt: R_est^T R_ref
    unit_ref = t_ref / np.maximum(COLMAP_EPS, np.linalg.norm(t_ref, axis=-1, keepdims=True))
    unit_est = t_est / np.maximum(COLMAP_EPS, np.linalg.norm(t_est, axis=-1, keepdims=True))
    d_t = np.degrees(np.arccos(np.clip(np.sum(unit_ref * unit_est, axis=-1), -1.0, 1.0)))
    off_diagonal = ~np.eye(len(reference), dtype=bool)
    return np.maximum(d_R, d_t)[off_diagonal]


def _relative_poses(poses: list) -> tuple[np.ndarray, np.ndarray]:
    """(K, K, 3, 3) and (K, K, 3): [i, j] is camera j's pose from camera i's."""
    R = np.array([p[0] for p in poses], dtype=float)
    t = np.array([p[1] for p in poses], dtype=float).reshape(-1, 3)
    R_ij = np.einsum("jab,icb->ijac", R, R)  # R_j R_i^T
    return R_ij, t[None, :, :] - np.einsum("ijab,ib->ija", R_ij, t)


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Degrees turned by rotations (..., 3, 3): atan2(|axis|, trace - 1), exact
    near 0 and 180 degrees where arccos of the trace alone loses digits."""
    axis = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.degrees(np.arctan2(np.linalg.norm(axis, axis=-1), np.trace(R, axis1=-2, axis2=-1) - 1.0))


def pose_auc(errors: np.ndarray, thresholds=POSE_AUC_THRESHOLDS) -> dict[str, float]:
    """``{"pose_auc<t>": AUC}``: the area under the recall curve of ``errors``
    up to each threshold ``t``, in per cent of ``t``.

    COLMAP's ``compute_auc`` (``benchmark/reconstruction/evaluation/utils.py``,
    ``min_error`` 0): the sorted errors with recall k/n at the k-th, (0, 0)
    prepended; the curve up to the last error <= t, then flat at that recall
    to t; the trapezoid rule over it.
    """
    errors = np.sort(np.asarray(errors, dtype=float))
    if not len(errors):
        raise ValueError("no pose errors to score")
    recalls = np.r_[0.0, (np.arange(len(errors)) + 1) / len(errors)]
    errors = np.r_[0.0, errors]
    aucs = {}
    for t in thresholds:
        last = np.searchsorted(errors, t, side="right")
        r = np.r_[recalls[:last], recalls[last - 1]]
        e = np.r_[errors[:last], t]
        aucs[f"pose_auc{t:g}"] = float(100.0 * np.trapezoid(r, x=e) / t)
    return aucs


def pose_recall(errors: np.ndarray, thresholds=POSE_AUC_THRESHOLDS) -> np.ndarray:
    """Per cent of ``errors`` at or below each threshold (COLMAP's
    ``compute_recall``): the recall curve, for a figure."""
    errors = np.asarray(errors, dtype=float)
    if not len(errors):
        raise ValueError("no pose errors to score")
    return 100.0 * np.mean(errors[None, :] <= np.asarray(thresholds, dtype=float)[:, None], axis=1)


def score_poses(reference, estimated: dict, random_state=0) -> dict[str, float]:
    """An estimate's poses scored against a reference's.

    ``reference`` is a :class:`mpe3d.harness.userdata.references.Reference`
    (its ``poses``, ``photos`` and ``unposed``; not imported here, the user's
    files are a room of their own), ``estimated`` is ``{photo name: (R, t)}``,
    matched to the reference's names exactly or else by base name (a
    ``folder/a.jpg`` of either side is ``a.jpg``). Returns the pose AUCs
    (:func:`pose_auc` of :func:`relative_pose_errors`, per cent), ``registered``
    (how many of the reference's photos, posed or not, the estimate poses) and
    its fraction of ``photos``, and ``centre_error``: the median distance of
    the estimated camera centres -R^T t, moved by :func:`robust_similarity`
    onto the reference's over the ``centres_scored`` photos both pose, in per
    cent of the diagonal of the reference centres' bounding box (NaN under 3).
    """
    listed = set(reference.poses) | set(getattr(reference, "unposed", ()))
    estimated = _on_reference_names(listed, {n: p for n, p in estimated.items()
                                             if np.all(np.isfinite(np.asarray(p[0], dtype=float)))})
    registered = sum(name in estimated for name in listed)
    shared = sorted(set(reference.poses) & set(estimated))
    scores = {**pose_auc(relative_pose_errors(reference.poses, estimated)), "registered": registered,
              "registered_fraction": registered / reference.photos if reference.photos else float("nan"),
              "photos": reference.photos, "centres_scored": len(shared), "centre_error": float("nan")}
    if len(shared) >= 3:
        ours = np.array([_centre(estimated[n]) for n in shared])
        theirs = np.array([_centre(reference.poses[n]) for n in shared])
        extent = float(np.linalg.norm(np.ptp([_centre(p) for p in reference.poses.values()], axis=0)))
        with np.errstate(divide="ignore", invalid="ignore"):  # centres in one place: NaN, said as such
            s, Q, t = robust_similarity(ours, theirs, np.random.default_rng(random_state))
            median = float(np.median(np.linalg.norm(s * ours @ Q.T + t - theirs, axis=1)))
        scores["centre_error"] = 100.0 * median / extent if extent > 0 else float("nan")
    return scores


def _centre(pose) -> np.ndarray:
    R, t = pose
    return -np.asarray(R, dtype=float).T @ np.asarray(t, dtype=float)


def base_name(name: str) -> str:
    """A photo's file name without any folder (either slash)."""
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def _on_reference_names(listed: set, estimated: dict) -> dict:
    """``estimated`` with each name the reference does not list renamed to the
    listed photo of its base name, where the base name is one photo's on both sides."""
    def by_base(names):
        found: dict[str, list[str]] = {}
        for name in names:
            found.setdefault(base_name(name), []).append(name)
        return found

    ours, theirs = by_base(n for n in estimated if n not in listed), by_base(n for n in listed if n not in estimated)
    renamed = {}
    for name, pose in estimated.items():
        base = base_name(name)
        unique = name not in listed and len(ours[base]) == 1 and len(theirs.get(base, ())) == 1
        renamed[theirs[base][0] if unique else name] = pose
    return renamed
