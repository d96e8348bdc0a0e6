"""The relative-pose AUC of COLMAP's benchmark: by hand, and against a transcription of COLMAP's code."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mpe3d.harness.scene.metrics import pose_auc, pose_recall, relative_pose_errors, score_poses
from tests.harness import colmap_evaluation as colmap_eval


def _pose(R, centre):
    """(R, t) of a camera at ``centre``: t = -R C."""
    return R, -R @ np.asarray(centre, dtype=float)


def _turn_z(degrees):
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


@pytest.fixture
def three():
    """Three cameras looking along z from points of the x-y plane, and the
    same with camera c turned 2 degrees about its axis (its centre kept)."""
    centres = {"a": [0.0, 0.0, 0.0], "b": [1.0, 0.0, 0.0], "c": [0.0, 1.0, 0.0]}
    reference = {n: _pose(np.eye(3), c) for n, c in centres.items()}
    estimated = {**reference, "c": _pose(_turn_z(2.0), centres["c"])}
    return reference, estimated


def test_a_camera_turned_2_degrees_errs_2_degrees_in_each_of_its_pairs(three):
    """Pairs (a, b) and (b, a): 0. A pair with c: its relative rotation is 2
    degrees off, and with c as the target its relative translation
    t_ij = R_j (C_i - C_j) is turned 2 degrees too (the baselines lie in the
    x-y plane, square to the axis); with c as the source it is unchanged."""
    reference, estimated = three
    errors = relative_pose_errors(reference, estimated)
    assert np.sort(errors) == pytest.approx([0, 0, 2, 2, 2, 2], abs=1e-9)


def test_the_auc_of_errors_0_0_2_2_2_2_by_hand():
    """Recall 2/6 from 0, then linearly (the trapezoid rule) to 3/6 at 2 and
    1 from 2 on: up to 1, 1/3 the whole way (the last segment flat at the
    recall reached); up to 3, 2 (1/3 + 1/2) / 2 + 1 = 11/6; up to 5, 5/6 + 3;
    up to 10, 5/6 + 8; each in per cent of the threshold."""
    aucs = pose_auc([0, 0, 2, 2, 2, 2])
    assert aucs == pytest.approx({"pose_auc1": 100 / 3, "pose_auc3": 100 * 11 / 18,
                                  "pose_auc5": 100 * 23 / 30, "pose_auc10": 100 * 53 / 60})


@pytest.mark.parametrize("errors, threshold, expected", [
    ([1.0], 3, 100 * 2.5 / 3),  # up to 1 linearly from 0 to recall 1, then 1
    ([3.0], 3, 50.0),  # an error at the threshold counts (side="right"): the triangle
    ([4.0, 180.0], 3, 0.0),  # nothing within the threshold
])
def test_the_auc_of_single_errors_by_hand(errors, threshold, expected):
    assert pose_auc(errors, (threshold,))[f"pose_auc{threshold}"] == pytest.approx(expected)


def test_recall_counts_the_errors_within_each_threshold():
    assert pose_recall([0, 0, 2, 2, 2, 4], (1, 2, 3, 5)) == pytest.approx([100 / 3, 500 / 6, 500 / 6, 100])


def _random_poses(rng, names):
    return {n: (Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)) for n in names}


def _noisy(rng, poses, degrees):
    return {n: (Rotation.from_rotvec(np.radians(degrees) * rng.normal(size=3)).as_matrix() @ R,
                t + 0.05 * rng.normal(size=3)) for n, (R, t) in poses.items()}


@pytest.mark.parametrize("seed", range(5))
def test_errors_and_aucs_are_colmaps_with_a_photo_unregistered_and_one_extra(seed):
    """Random poses, a few degrees of noise; photo p3 not registered (its pairs
    180), and photo x registered but not in the reference (COLMAP's "registered
    outlier": its pairs 180 too)."""
    rng = np.random.default_rng(seed)
    reference = _random_poses(rng, [f"p{k}" for k in range(7)])
    estimated = _noisy(rng, {n: p for n, p in reference.items() if n != "p3"}, 3.0)
    estimated["x"] = (np.eye(3), np.zeros(3))
    ours = relative_pose_errors(reference, estimated)
    theirs = colmap_eval.compute_grouped_rel_errors(reference, estimated)
    assert len(ours) == len(theirs) == 7 * 6 + 2 * 6  # 12 pairs with p3, 12 with x
    assert np.sort(ours) == pytest.approx(np.sort(theirs), abs=1e-7)  # arccos near 0: ~1e-8 rad
    thresholds = (0.5, 1, 3, 5, 10)
    assert list(pose_auc(ours, thresholds).values()) == pytest.approx(
        colmap_eval.compute_auc(theirs, thresholds), abs=1e-9)


def test_a_zero_relative_translation_is_colmaps_90_degrees():
    reference = {"a": _pose(np.eye(3), [0, 0, 0]), "b": _pose(np.eye(3), [0, 0, 0])}
    ours = relative_pose_errors(reference, reference)
    assert ours == pytest.approx(colmap_eval.compute_grouped_rel_errors(reference, reference)) and ours[0] == 90


def test_nothing_registered_is_all_180():
    reference = {f"p{k}": _pose(np.eye(3), [k, 0, 0]) for k in range(3)}
    assert np.all(relative_pose_errors(reference, {}) == 180) and len(relative_pose_errors(reference, {})) == 6
    assert relative_pose_errors({"a": reference["p0"]}, {}).tolist() == [180.0]  # no pair: COLMAP's [180]
    assert pose_auc([180.0])["pose_auc10"] == 0


def _reference(poses, photos=None, unposed=()):
    return SimpleNamespace(poses=poses, photos=photos or len(poses) + len(unposed), unposed=unposed)


def test_a_similar_world_scores_100_and_no_centre_error(rng):
    """The relative poses do not see the world's frame or scale: the same
    cameras in a turned, scaled, moved world are perfect."""
    reference = _random_poses(rng, [f"p{k}" for k in range(6)])
    Q, s, shift = Rotation.random(random_state=rng).as_matrix(), 3.0, rng.normal(size=3)
    # x' = s Q x + shift: R' = R Q^T, t' = s t - R Q^T shift
    moved = {n: (R @ Q.T, s * t - R @ Q.T @ shift) for n, (R, t) in reference.items()}
    scores = score_poses(_reference(reference), moved)
    assert scores["pose_auc1"] == pytest.approx(100, abs=1e-4)
    assert scores["centre_error"] == pytest.approx(0, abs=1e-9) and scores["centres_scored"] == 6
    assert scores["registered"] == 6 and scores["registered_fraction"] == 1


def test_names_match_by_base_name_and_unposed_photos_count_as_registered(rng):
    reference = _random_poses(rng, ["a.jpg", "b.jpg", "c.jpg"])
    estimated = {f"images/{n}": p for n, p in reference.items()} | {"d.jpg": (np.eye(3), np.zeros(3))}
    scores = score_poses(_reference(reference, unposed=("d.jpg",)), estimated)
    assert scores["registered"] == 4 and scores["photos"] == 4
    # d.jpg is not posed in the reference: its 6 pairs are 180, the other 6 exact
    assert scores["pose_auc1"] == pytest.approx(50, abs=1e-4)


def test_fewer_than_3_shared_centres_give_no_centre_error(rng):
    reference = _random_poses(rng, ["a", "b", "c"])
    scores = score_poses(_reference(reference), {"a": reference["a"], "b": reference["b"]})
    assert np.isnan(scores["centre_error"]) and scores["centres_scored"] == 2 and scores["registered"] == 2
