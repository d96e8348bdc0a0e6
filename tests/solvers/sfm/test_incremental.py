"""The incremental weak-perspective start: grown view by view, robust at each step."""
import numpy as np
import pytest

from mpe3d.harness.scene.metrics import roa
from mpe3d.solvers.sfm import bundle
from mpe3d.solvers.sfm.cameras import affine_cameras, exp_so3
from mpe3d.solvers.sfm.incremental import FLOOR, incremental_start
from mpe3d.solvers.sfm.tracks import residual_lengths

N, K, WINDOW = 200, 24, 6


def _turntable(rng, noise=0.5, zoom=0.1, truth=False):
    """K views around the y axis, 15 degrees apart, each point seen in WINDOW
    consecutive views: a long sequence with no track in every view."""
    X = rng.standard_normal((N, 3)) * np.array([100, 60, 100])
    angles = np.radians(15) * np.arange(K)
    R = exp_so3(np.column_stack([0.1 * np.ones(K), angles, np.zeros(K)]))
    cameras = affine_cameras("scaled", R[:, :2], np.exp(zoom * rng.standard_normal(K)),
                             300 + 10 * rng.standard_normal((K, 2)))
    first = rng.integers(0, K, N)
    view = (first[:, None] + np.arange(WINDOW)).ravel() % K
    point = np.repeat(np.arange(N), WINDOW)
    z = cameras.project(X, view, point) + noise * rng.standard_normal((len(view), 2))
    tracks = bundle.Tracks(view, point, z, N, K)
    return (tracks, X) if truth else tracks


def _swapped(tracks, share, rng):
    z = tracks.z.copy()
    for row in rng.choice(len(z), int(share * len(z)), replace=False):
        z[row] = tracks.z[rng.choice(np.flatnonzero(tracks.view == tracks.view[row]))]
    # the start leaves out only what is beyond FLOOR of the image: twice that is far
    far = np.linalg.norm(z - tracks.z, axis=1) > 2 * FLOOR * np.ptp(tracks.z, axis=0).max()
    return bundle.Tracks(tracks.view, tracks.point, z, N, K), far


def test_a_sequence_is_grown_to_every_view_at_the_noise_level(rng):
    tracks = _turntable(rng)
    X, cameras, left_out = incremental_start(tracks)
    length = residual_lengths(X, cameras, tracks)
    # Rayleigh median of 0.5 px noise: 0.59 px; the start need not be polished
    assert np.median(length) < 1.2 and not left_out.any()


def test_orthographic_views_give_the_cloud_at_its_own_size(rng):
    """Weak perspective leaves the cloud's size free; the start puts it at the
    views' mean scale, so orthographic views (scale 1) get the true cloud up to
    a rotation, as the factorisation's start does."""
    tracks, truth = _turntable(rng, noise=0.0, zoom=0.0, truth=True)
    X, cameras, _ = incremental_start(tracks)
    assert np.exp(np.mean(np.log(cameras.scale()))) == pytest.approx(1.0)
    assert roa(X, truth) < 1e-6 * np.ptp(truth, axis=0).max()


def test_wrong_matches_neither_bend_the_start_nor_stay_in_it(rng):
    clean = _turntable(rng)
    tracks, far = _swapped(clean, 0.05, rng)
    X, cameras, left_out = incremental_start(tracks)
    length = residual_lengths(X, cameras, tracks)
    assert np.median(length[~far]) < 1.2
    assert left_out[far].mean() >= 0.9 and left_out[~far].mean() <= 0.01


def test_views_that_share_no_points_give_no_start(rng):
    tracks = _turntable(rng)
    cut = (tracks.view < K // 2) == (tracks.point < N // 2)  # two halves, no point in both
    keep = np.bincount(tracks.point[cut], minlength=N)[tracks.point[cut]] >= 2
    rows = np.flatnonzero(cut)[keep]
    assert incremental_start(tracks.subset(rows)) is None


def test_two_views_give_no_start(rng):
    tracks = _turntable(rng)
    two = tracks.subset(np.flatnonzero(tracks.view < 2))
    assert incremental_start(bundle.Tracks(two.view, two.point, two.z, N, 2)) is None
