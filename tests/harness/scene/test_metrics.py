import numpy as np
import pytest
from scipy.spatial.distance import cdist

from mpe3d.harness.scene.metrics import align_ransac4, align_rigid, chamfer, earth_movers, evaluate, roa
from mpe3d.harness.scene.viewpoints import rotation


def test_chamfer_is_zero_on_identical_clouds(rng):
    pts = rng.normal(size=(300, 3))
    scores = chamfer(pts, pts[rng.permutation(300)])
    assert scores == {"cd": 0.0, "cd_mean": 0.0, "cd_x100": 0.0}


def test_chamfer_on_a_known_offset():
    a = np.zeros((1, 3))
    b = np.array([[0.0, 0.0, 0.5]])
    scores = chamfer(a, b)
    assert scores["cd"] == pytest.approx(0.5)  # 0.25 each way, squared distances
    assert scores["cd_x100"] == pytest.approx(100.0)


@pytest.mark.parametrize("reflect", [False, True])
def test_roa_unchanged_by_rigid_motion_and_reflection(rng, reflect):
    truth = rng.normal(size=(200, 3))
    recon = truth + 0.01 * rng.normal(size=truth.shape)
    base = roa(recon, truth)
    Q = rotation(0.4, -0.9, 2.2)
    if reflect:
        Q = Q @ np.diag([1.0, 1.0, -1.0])
    moved = recon @ Q.T + np.array([3.0, -1.0, 0.5])
    assert roa(moved, truth) == pytest.approx(base, rel=1e-9)
    assert roa(truth @ Q.T, truth) < 1e-12
    assert np.allclose(align_rigid(truth @ Q.T - 7.0, truth), truth, atol=1e-12)


def test_emd_is_pots_exact_transport(rng):
    """Clouds of one size are scored by the assignment; POT's network simplex
    (an independent exact solver) reaches the same optimum."""
    import ot

    for n in (3, 7, 12, 300):
        a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        M = cdist(a, b)
        plan = ot.emd(np.full(n, 1.0 / n), np.full(n, 1.0 / n), M)
        scores = earth_movers(a, b)
        assert scores["emd_mean"] == pytest.approx(np.sum(plan * M), rel=1e-12)
        assert scores["emd"] == pytest.approx(n * np.sum(plan * M), rel=1e-12)
    a = rng.normal(size=(12, 3))  # a shuffled copy: the assignment undoes the shuffle
    assert earth_movers(a, a[rng.permutation(12)])["emd"] == 0.0


def test_ransac4_recovers_an_affine_map(rng):
    truth = rng.normal(size=(100, 3))
    A = np.array([[1.2, 0.1, 0.0], [0.0, 0.8, 0.3], [0.2, 0.0, 1.1]])
    recon = (truth - 0.5) @ np.linalg.inv(A).T
    aligned = align_ransac4(recon, truth, rng, trials=50)
    assert np.allclose(aligned, truth, atol=1e-8)


def test_evaluate_reports_every_metric(rng):
    truth = rng.normal(size=(64, 3))
    scores, aligned = evaluate(truth, truth @ rotation(1, 2, 3).T, "rigid", 0)
    assert set(scores) >= {"cd", "cd_mean", "emd", "emd_mean", "roa"}
    assert all(v < 1e-10 for v in scores.values())
    assert np.allclose(aligned, truth, atol=1e-12)


def test_the_tests_alignment_counts_errors_that_cancel_between_axes(rng):
    """The tests' one alignment helper: a point moved by (e, -e, 0) is off by
    e*sqrt(2), not by the zero that summing signed axes before squaring gave
    (the copy in test_keypoints did; its errors cancelled and passed)."""
    from tests.helpers import similarity_residuals, similarity_rms

    truth = rng.normal(size=(50, 3))
    moved = truth.copy()
    moved[7] += [0.3, -0.3, 0.0]
    assert similarity_residuals(moved, truth)[7] > 0.3
    assert similarity_rms(moved, truth) > 0.3 * np.sqrt(2) / np.sqrt(50) * 0.9
    mirrored = truth * [1, 1, -1]
    assert similarity_rms(mirrored, truth) > 0.1  # a mirror image is another shape ...
    assert similarity_rms(mirrored, truth, mirror=True) < 1e-12  # ... unless mirrors are allowed
