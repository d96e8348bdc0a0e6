"""COLMAP's benchmark metric, transcribed for the tests to hold mpe3d's to.

A line-by-line transcription of ``benchmark/reconstruction/evaluation/utils.py``
(``compute_grouped_rel_errors`` for one estimated model and one reference
component, ``compute_rel_pose_error``, ``compute_auc``) and ``geometry.py``
(``normalize_vec``, ``vec_angular_dist_deg``) of COLMAP, at commit
5d968cf38aa2574fd284b0dc86c3d58d124940b3. ``pycolmap.Rigid3d`` is replaced by
``(R, t)`` pairs (``a * b``, ``inverse``) and ``Rotation3d.angle()`` by scipy's
rotation magnitude, so that nothing here shares code with mpe3d's version.
"""
import collections
import itertools

import numpy as np
from scipy.spatial.transform import Rotation


def _compose(a, b):  # Rigid3d a * b
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def _inverse(a):  # Rigid3d.inverse()
    return a[0].T, -a[0].T @ a[1]


def normalize_vec(vec, eps=1e-10):
    return vec / max(eps, float(np.linalg.norm(vec)))


def vec_angular_dist_deg(vec1, vec2):
    cos_dist = np.clip(np.dot(normalize_vec(vec1), normalize_vec(vec2)), -1, 1)
    return np.rad2deg(np.arccos(cos_dist))


def compute_rel_pose_error(tgt_from_src_est, tgt_from_src_gt, min_proj_center_dist):
    estimated_from_gt = _compose(_inverse(tgt_from_src_est), tgt_from_src_gt)
    if np.linalg.norm(tgt_from_src_gt[1]) < min_proj_center_dist:
        dt = 0.0
    else:
        dt = vec_angular_dist_deg(tgt_from_src_est[1], tgt_from_src_gt[1])
    dR = np.rad2deg(Rotation.from_matrix(estimated_from_gt[0]).magnitude())
    return dt, dR


def compute_grouped_rel_errors(gt_cam_from_world: dict, est_cam_from_world: dict, min_proj_center_dist=0.0):
    """One sub-model (``est_cam_from_world``), every GT image in component 0."""
    tgt_from_src_est_edges = collections.defaultdict(list)
    for src_name, tgt_name in itertools.permutations(est_cam_from_world, 2):
        tgt_from_src_est = _compose(est_cam_from_world[tgt_name], _inverse(est_cam_from_world[src_name]))
        tgt_from_src_est_edges[(src_name, tgt_name)].append(tgt_from_src_est)
    gt_edges = set(itertools.permutations(list(gt_cam_from_world), 2))
    errors = []
    for edge in set(tgt_from_src_est_edges) | gt_edges:
        src_name, tgt_name = edge
        tgt_from_src_ests = tgt_from_src_est_edges.get(edge, [])
        if edge in gt_edges:
            tgt_from_src_gt = _compose(gt_cam_from_world[tgt_name], _inverse(gt_cam_from_world[src_name]))
            if not tgt_from_src_ests:
                errors.append(180.0)
            for tgt_from_src_est in tgt_from_src_ests:
                dt, dR = compute_rel_pose_error(tgt_from_src_est, tgt_from_src_gt, min_proj_center_dist)
                errors.append(max(dt, dR))
        else:
            errors.extend(180.0 for _ in tgt_from_src_ests)
    if not errors:
        return np.array([180.0])
    return np.array(errors)


def compute_auc(errors, thresholds, min_error=0):
    num_elems = len(errors)
    errors = np.sort(errors)
    recalls = (np.arange(num_elems) + 1) / num_elems
    if min_error > 0:
        min_index = np.searchsorted(errors, min_error, side="right")
        min_recall = min_index / num_elems
        recalls = np.r_[min_recall, min_recall, recalls[min_index:]]
        errors = np.r_[0, min_error, errors[min_index:]]
    else:
        recalls = np.r_[0, recalls]
        errors = np.r_[0, errors]
    aucs = np.zeros(len(thresholds), dtype=np.float64)
    for i, t in enumerate(thresholds):
        last_index = np.searchsorted(errors, t, side="right")
        r = np.r_[recalls[:last_index], recalls[last_index - 1]]
        e = np.r_[errors[:last_index], t]
        auc = np.trapezoid(r, x=e) / t
        aucs[i] = auc * 100
    return aucs
