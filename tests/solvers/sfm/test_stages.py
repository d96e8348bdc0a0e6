"""Bundle adjustment's stages: each runs when its cheap test says the data need it, and says why."""
import numpy as np
import pytest

from mpe3d.harness.scene.rendering import PhotoCameras, spiral_cameras
from mpe3d.solvers.sfm import bundle, stages
from tests.helpers import random_views

N, K = 300, 8


def _ran(result) -> list[str]:
    return [s.name for s in result.stages if s.ran]


def _why(result, name: str) -> str:
    return next(s.why for s in result.stages if s.name == name)


def _spiral_tracks(rng, views=12, points=400, noise=0.3, k1=0.0):
    """Pinhole photos of a sphere of points from the photo spiral (400 px), each
    point seen by the cameras facing it, through a lens of radial distortion k1."""
    normals = rng.normal(size=(points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    X = 0.4 * normals
    c = spiral_cameras(views, turns=views / 25, fill=1.2)
    cams = PhotoCameras(c.rotations, c.translations, c.focal, c.width, c.height, (k1, 0.0))
    facing = np.einsum("kpd,pd->kp", cams.centres[:, None, :] - X[None], normals) > 0.2
    view, point = np.nonzero(facing)
    z = cams.project(X)[0][view, point] + noise * rng.normal(size=(len(view), 2))
    return bundle.Tracks(view, point, z, points, views), X, cams


def test_exact_orthographic_views_need_no_pinhole(rng):
    """The affine fit explains them to the last digits: nothing can fit better,
    and no pinhole is fitted to find that out."""
    _, _, view, point, z = random_views(rng, "orthographic", N, K, turn=0.6, noise=0.0)
    result = bundle.bundle_adjust(bundle.Tracks(view, point, z, N, K))
    assert result.camera == "scaled" and result.rms() < 1e-8
    assert "grown pinhole" not in _ran(result) and "pinhole from the affine start" not in _ran(result)
    assert "exactly" in _why(result, "pinhole")


def test_noisy_affine_views_are_scaled_at_the_noise_level(rng):
    """Half a pixel of noise: two views at a time are as near affine epipolar
    geometry as to any epipolar geometry, and the scaled fit's median residual
    is within AT_NOISE of the noise they tell: the pinhole is never fitted."""
    _, _, view, point, z = random_views(rng, "scaled", N, K, turn=0.6, noise=0.5)
    result = bundle.bundle_adjust(bundle.Tracks(view, point, z, N, K))
    assert result.camera == "scaled"
    assert result.noise == pytest.approx(0.5, rel=0.3)
    assert result.affine_misfit < stages.PERSPECTIVE * result.noise
    assert "noise" in _why(result, "pinhole") and "grown pinhole" not in _ran(result)
    assert set(result.rms_by_camera) == {"scaled"}


def test_close_pinhole_photos_start_grown_and_skip_the_affine_start(rng):
    """Close photos from round an object: two views already show perspective,
    so the pinhole grown view by view goes first, fits at the noise level,
    and neither the affine start nor a second opinion runs."""
    tracks, X, _ = _spiral_tracks(rng)
    result = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0))
    assert result.camera == "perspective"
    assert result.affine_misfit > stages.PERSPECTIVE * result.noise
    assert _ran(result)[:2] == ["suspects", "grown pinhole"]
    assert "affine start" not in _ran(result) and "second pinhole" not in _ran(result)
    assert "no prior focal length" in _why(result, "grown pinhole")
    assert result.rms() < 0.5


def test_a_doubtful_first_pinhole_gets_a_second_opinion(rng):
    """A principal point 160 px off leaves the grown pinhole's residuals at
    3 times the noise two views tell, over DOUBTFUL: the pinhole from the
    affine start is fitted too, and the better kept; with the right one, no
    second opinion is needed."""
    tracks, _, _ = _spiral_tracks(rng, noise=0.1)
    doubted = bundle.bundle_adjust(tracks, "perspective", principal_point=(330.0, 120.0))
    assert {"affine start", "pinhole from the affine start", "second pinhole"} <= set(_ran(doubted))
    assert "doubtful" in _why(doubted, "second pinhole")
    trusted = bundle.bundle_adjust(tracks, "perspective", principal_point=(200.0, 200.0))
    assert "second pinhole" not in _ran(trusted)


def test_the_lens_is_kept_where_the_keypoints_show_it_and_not_elsewhere(rng):
    """The information criterion on the robust residuals: a lens of k1 = -0.3
    moves the frame's edges by pixels, far beyond 0.2 px of noise; without
    one, the radial camera gains about 2 (chi-square, 2 degrees of freedom)
    against a penalty of 2 log n."""
    plain, _, _ = _spiral_tracks(rng, noise=0.2)
    lens, _, _ = _spiral_tracks(np.random.default_rng(1), noise=0.2, k1=-0.3)
    kept = bundle.bundle_adjust(plain, principal_point=(200.0, 200.0))
    distorted = bundle.bundle_adjust(lens, principal_point=(200.0, 200.0))
    assert kept.camera == "perspective" and "the plain pinhole" in _why(kept, "lens")
    assert distorted.camera == "radial" and "the radial camera" in _why(distorted, "lens")
    assert distorted.cameras.distortion()[0][0] == pytest.approx(-0.3, abs=0.05)


def test_a_prior_focal_length_starts_the_grown_pinhole(rng):
    tracks, _, cams = _spiral_tracks(rng)
    result = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0), focal=cams.focal)
    assert f"prior focal length {cams.focal:.4g} px" in _why(result, "grown pinhole")
    assert result.cameras.focal()[0] == pytest.approx(cams.focal, rel=0.01)


def test_keeping_every_observation_keeps_the_grown_start(rng):
    """outlier_threshold=inf drops nothing, and no longer turns the grown
    pinhole off: its fit is solved on every observation of its views."""
    tracks, _, _ = _spiral_tracks(rng)
    result = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0), outlier_threshold=np.inf)
    assert "grown pinhole" in _ran(result) and not result.dropped.any()
    assert "wrong matches" not in _ran(result)
    assert result.counted.sum() == result.placed[tracks.point].sum()


def test_random_state_reaches_the_random_choices(rng):
    """The same seed gives the same bits; another one other RANSAC samples
    (the two-view tests' and the grown start's), so other last digits."""
    tracks, _, _ = _spiral_tracks(rng)
    one = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0), random_state=1)
    again = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0), random_state=1)
    other = bundle.bundle_adjust(tracks, principal_point=(200.0, 200.0), random_state=2)
    assert np.array_equal(one.points, again.points)
    assert not np.array_equal(one.points, other.points)
    assert np.abs(one.rms() - other.rms()) < 1e-3  # the same optimum, reached by other samples


def test_bad_options_are_refused_in_one_line():
    from mpe3d.errors import MpeError

    for bad in ({"focal": -1.0}, {"random_state": -1}, {"principal_point": (1.0,)}, {"camera": "fisheye"},
                {"outlier_threshold": 0.0}):
        with pytest.raises(MpeError) as caught:
            stages.BundleOptions(**bad)
        assert "\n" not in str(caught.value) and next(iter(bad)) in str(caught.value)
