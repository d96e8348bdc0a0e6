import numpy as np
import pytest

from mpe3d.harness.scene.viewpoints import angle_bins, draw_angles, projections, rotation, rotations


def test_rotations_are_proper_orthonormal(rng):
    angles = rng.uniform(-360, 360, size=(200, 3))
    R = rotations(angles)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-12)
    P = projections(R)
    assert P.shape == (200, 2, 3)
    assert np.allclose(P @ np.swapaxes(P, 1, 2), np.eye(2), atol=1e-12)


def test_rotation_is_rz_ry_rx():
    a, b, g = 0.3, -1.1, 2.0
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(g), -np.sin(g)], [0, np.sin(g), np.cos(g)]])
    assert np.allclose(rotation(a, b, g), Rz @ Ry @ Rx, atol=1e-14)


@pytest.mark.parametrize("K", [2, 3, 4, 5, 8])
@pytest.mark.parametrize("band", [360.0, 90.0, 1.0])
def test_angles_fall_in_their_bins(K, band, rng):
    bins = angle_bins(K, band)
    assert bins.shape == (K, 2)
    for _ in range(50):
        angles = draw_angles(K, band, rng)
        lo, hi = bins.min(axis=1, keepdims=True), bins.max(axis=1, keepdims=True)
        assert np.all((angles >= lo) & (angles <= hi))


def test_bins_follow_the_paper():
    width = 360 / 4
    assert np.allclose(angle_bins(4, 360), [[0, width], [width, 2 * width],
                                            [0, -width], [-width, -2 * width]])
    # odd K: the bins of K + 1 = 6, last one dropped
    w6 = 360 / 6
    assert np.allclose(angle_bins(5, 360), [[0, w6], [w6, 2 * w6], [2 * w6, 3 * w6],
                                            [0, -w6], [-w6, -2 * w6]])


def test_sphere_layout_spreads_cameras_evenly(rng):
    from mpe3d.harness.scene.viewpoints import sphere_rotations

    R = sphere_rotations(5, rng)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    towards = -R[:, 2]
    cosines = towards @ towards.T
    nearest = np.degrees(np.arccos(np.max(cosines - 2 * np.eye(5), axis=1)))
    assert nearest.min() > 60  # no two of 5 cameras nearly coincide (a band draw can give 0)
