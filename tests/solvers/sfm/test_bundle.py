"""Bundle adjustment of keypoints: camera models, their Jacobians, the start and the solve."""
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from mpe3d.errors import MpeError
from mpe3d.solvers.degenerate import DegenerateWarning
from mpe3d.solvers.factorize import metric_upgrade_pd
from mpe3d.solvers.linalg import matvec_by_group
from mpe3d.solvers.sfm import bundle, camera_fits
from mpe3d.solvers.sfm.cameras import (
    AFFINE,
    Cameras,
    affine_cameras,
    exp_so3,
    hat,
    radial_cameras,
    right_jacobian,
    with_distortion,
)
from mpe3d.solvers.sfm.triangulation import widest_angles
from tests.helpers import SHARED, blas_fuses_small_products, similarity_rms

N, K = 60, 6


def _tracks(cameras, rng, keep=0.7, noise=0.0):
    X = rng.standard_normal((N, 3)) * 100
    view = np.repeat(np.arange(K), N)
    point = np.tile(np.arange(N), K)
    seen = rng.random(len(view)) < keep
    seen[point < 8] = True  # a core every view shares, so the views tie together
    seen[(view - point) % K < 3] = True  # and every point in at least 3 views
    view, point = view[seen], point[seen]
    z = cameras.project(X, view, point) + noise * rng.standard_normal((len(view), 2))
    return X, bundle.Tracks(view, point, z, N, K)


def _cameras(model, rng, focal=900.0):
    R = exp_so3(rng.standard_normal((K, 3)))
    scale = np.exp(0.3 * rng.standard_normal(K)) if model != "orthographic" else np.ones(K)
    return affine_cameras(model, R[:, :2], scale, 300 + 50 * rng.standard_normal((K, 2)),
                          focal=focal, principal_point=[320.0, 240.0])


def _similarity_error(X, truth):
    """RMS distance after the best similarity (mirror allowed), relative to the size."""
    return similarity_rms(X, truth, mirror=True) / np.sqrt(np.mean(np.sum((truth - truth.mean(0)) ** 2, 1)))


def _random_cameras(model, rng):
    """K cameras of ``model`` (``-per-view``: focal lengths per view) in general position."""
    if model == "affine":
        return Cameras(AFFINE, np.broadcast_to(np.eye(3), (K, 3, 3)),
                       rng.standard_normal((K, 8)), np.zeros(0), np.zeros(2))
    R = exp_so3(rng.standard_normal((K, 3)))
    pinhole = model.startswith(("perspective", "radial"))
    cameras = affine_cameras("perspective" if pinhole else model, R[:, :2],
                             np.exp(rng.standard_normal(K) / 5), rng.standard_normal((K, 2)),
                             focal=5.0, principal_point=[0.1, 0.2],
                             shared_focal=model in ("perspective", "radial"))
    if model.startswith("radial"):
        cameras = with_distortion(cameras)
        k = cameras.shared[1:] if cameras.shared.size else cameras.params[:, 7:]
        k[...] = 0.1 * rng.standard_normal(k.shape)
    cameras.params[:, :3] = 0.3 * rng.standard_normal((K, 3))  # away from the anchor
    return cameras


@pytest.mark.parametrize("model", ["affine", "orthographic", "scaled", "perspective",
                                   "perspective-per-view", "radial", "radial-per-view"])
def test_analytic_jacobians_match_finite_differences(model, rng):
    cameras = _random_cameras(model, rng)
    X = rng.standard_normal((N, 3))
    view, point = np.repeat(np.arange(K), N), np.tile(np.arange(N), K)
    d_x, d_view, d_shared = cameras.jacobian_blocks(X, view, point)
    v, h = cameras.vector(), 1e-6
    for j in range(len(v)):
        up, down = v.copy(), v.copy()
        up[j] += h
        down[j] -= h
        numeric = (cameras.with_vector(up).project(X, view, point)
                   - cameras.with_vector(down).project(X, view, point)) / (2 * h)
        analytic = np.zeros_like(numeric)
        if j < K * cameras.per_view:
            k, c = divmod(j, cameras.per_view)
            analytic[view == k] = d_view[view == k, :, c]
        else:
            analytic = d_shared[:, :, j - K * cameras.per_view]
        assert np.abs(numeric - analytic).max() < 1e-7, (model, j)
    for c in range(3):
        up, down = X.copy(), X.copy()
        up[:, c] += h
        down[:, c] -= h
        numeric = (cameras.project(up, view, point) - cameras.project(down, view, point)) / (2 * h)
        assert np.abs(numeric - d_x[:, :, c]).max() < 1e-7


def _numpy_pose_blocks(cameras, X, view, point):
    """The numpy formulation that kernels.pose_jacobians replaced."""
    T, x = len(view), X[point]
    R = cameras.current_rotations()[view]
    q = np.einsum("tij,tj->ti", R, x)
    dq_dw = -R @ hat(x) @ right_jacobian(cameras.params[:, :3])[view]
    d_view, d_shared = np.zeros((T, 2, cameras.per_view)), np.zeros((T, 2, cameras.shared.size))
    if cameras.model != "perspective":
        s = cameras.scale()[view, None, None]
        d_view[:, :, :3] = s * dq_dw[:, :2]
        d_view[:, 0, 3] = d_view[:, 1, 4] = 1.0
        if cameras.model == "scaled":
            d_view[:, :, 5] = s[:, :, 0] * q[:, :2]
        return s * R[:, :2], d_view, d_shared
    p = q + cameras.params[view, 3:6]
    f, n = cameras.focal()[view], p[:, :2] / p[:, 2:3]
    dn_dp = np.zeros((T, 2, 3))
    dn_dp[:, 0, 0] = dn_dp[:, 1, 1] = 1 / p[:, 2]
    dn_dp[:, :, 2] = -n / p[:, 2:3]
    du_dp = (f[:, None, None] * np.eye(2)) @ dn_dp
    d_view[:, :, :3], d_view[:, :, 3:6] = du_dp @ dq_dw, du_dp
    (d_shared if cameras.shared.size else d_view[:, :, 6:])[...] = (f[:, None] * n)[:, :, None]
    return du_dp @ R, d_view, d_shared


def _numpy_sums_as_the_kernel_does(rng) -> bool:
    """Whether numpy's BLAS fuses small products and einsum sums R x as
    (r0 x0 + r2 x2) + r1 x1 (numpy 2's einsum): then the kernel must give
    numpy's bits."""
    R, x = rng.standard_normal((40, 3, 3)), rng.standard_normal((40, 3))
    paired = (R[:, :, 0] * x[:, None, 0] + R[:, :, 2] * x[:, None, 2]) + R[:, :, 1] * x[:, None, 1]
    return blas_fuses_small_products() and np.array_equal(np.einsum("tij,tj->ti", R, x), paired)


@pytest.mark.parametrize("model", ["affine", "scaled", "perspective", "radial"])
def test_compiled_projections_are_the_per_view_products(model, rng):
    """project's R x (kernels.grouped_matvecs) against matvec_by_group's one
    BLAS product per view: the same bits where BLAS fuses small products,
    also for a view with a single observation (which BLAS forms by gemv),
    else to rounding."""
    cameras = _random_cameras(model, rng)
    X = 100 * rng.standard_normal((N, 3))
    view = np.repeat(np.arange(K), [N, N, N, 1, 2, 0])  # a view seen once, one twice, one never
    point = np.concatenate([rng.permutation(N) for _ in range(3)] + [[7], [3, 9]])
    got = cameras.project(X, view, point)
    if model == "affine":
        want = matvec_by_group(cameras.params[:, :6].reshape(-1, 2, 3), view, X[point]) \
            + cameras.params[view, 6:8]
    else:
        q = matvec_by_group(cameras.current_rotations(), view, X[point])
        if model == "scaled":
            want = cameras.scale()[view, None] * q[:, :2] + cameras.params[view, 3:5]
        else:  # the pinholes: the same q through the same numpy steps
            want = _pinhole_images(cameras, q, view)
    assert np.isfinite(got).any()
    if blas_fuses_small_products():
        assert np.array_equal(got, want, equal_nan=True)
    else:
        assert np.allclose(got, want, rtol=1e-12, atol=1e-9, equal_nan=True)


def _pinhole_images(cameras, q, view):
    p = q + cameras.params[view, 3:6]
    n = p[:, :2] / np.where(p[:, 2:3] > 0, p[:, 2:3], np.nan)  # behind the camera: no image
    if cameras.model == "radial":
        k = cameras.distortion()[view]
        r2 = np.sum(n ** 2, axis=1, keepdims=True)
        n = n * (1 + k[:, :1] * r2 + k[:, 1:] * r2 ** 2)
    return cameras.focal()[view, None] * n + cameras.principal_point


def test_compiled_widest_angles_are_the_pass_over_gaps(rng):
    """widest_angles (kernels.lowest_cosines) against the numpy pass it
    replaced, rays of long and short tracks, as lines and not, one NaN ray:
    the same bits where einsum sums three columns as the kernel does."""
    rays = rng.standard_normal((3000, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    point = rng.integers(0, 120, size=3000)  # tracks of ~25 rays
    point[:40] = 500  # and one of 40 among 600 points, most of them with none
    rays[100] = np.nan
    for lines in (False, True):
        order = np.argsort(point, kind="stable")
        p, u = point[order], rays[order]
        lowest = np.ones(600)
        with np.errstate(invalid="ignore"):
            for gap in range(1, len(p)):
                same = p[gap:] == p[:-gap]
                if not same.any():
                    break
                cos = np.einsum("ti,ti->t", u[gap:][same], u[:-gap][same])
                np.minimum.at(lowest, p[gap:][same], np.abs(cos) if lines else cos)
            want = np.degrees(np.arccos(np.clip(lowest, -1.0, 1.0)))
        got = widest_angles(rays, point, 600, lines)
        if _numpy_sums_as_the_kernel_does(rng):
            assert np.array_equal(got, want, equal_nan=True)
        else:
            assert np.allclose(got, want, rtol=1e-12, atol=1e-9, equal_nan=True)
        assert np.isnan(got[point[100]]) and (got[np.bincount(point, minlength=600) < 2] == 0).all()


@pytest.mark.parametrize("model", ["orthographic", "scaled", "perspective", "perspective-per-view"])
def test_compiled_pose_jacobians_are_the_numpy_formulation(model, rng):
    """jacobian_blocks of the compiled models against the numpy formulation:
    the same bits where numpy sums as the kernel does, else to rounding."""
    cameras = _random_cameras(model, rng)
    X = 100 * rng.standard_normal((N, 3))
    if cameras.model == "perspective":
        cameras.params[:, 5] += 1000.0  # every point in front
    view, point = np.repeat(np.arange(K), N), np.tile(np.arange(N), K)
    order = rng.permutation(len(view))  # observations in no particular order
    view, point = view[order], point[order]
    got = cameras.jacobian_blocks(X, view, point)
    expected = _numpy_pose_blocks(cameras, X, view, point)
    exact = _numpy_sums_as_the_kernel_does(rng)
    for a, b in zip(got, expected):
        assert a.shape == b.shape
        if exact:
            assert np.array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


@pytest.mark.parametrize("model", ["orthographic", "scaled"])
def test_noise_free_weak_perspective_views_are_solved_exactly(model, rng):
    truth, tracks = _tracks(_cameras(model, rng), rng)
    result = bundle.bundle_adjust(tracks, model)
    assert result.converged
    assert result.rms() < 1e-8 * 300
    assert _similarity_error(result.points, truth) < 1e-9


def test_noise_free_pinhole_views_are_solved_exactly_with_their_focal_length(rng):
    truth, tracks = _tracks(_cameras("perspective", rng, focal=600.0), rng, keep=0.8)
    weak = bundle.bundle_adjust(tracks, "scaled")
    result = bundle.bundle_adjust(tracks, "perspective", principal_point=[320.0, 240.0])
    assert result.converged and result.rms() < 1e-6
    assert result.rms() < 1e-3 * weak.rms()  # the model that made the data explains them
    assert result.cameras.focal()[0] == pytest.approx(600.0, rel=1e-6)
    assert _similarity_error(result.points, truth) < 1e-8


def test_a_point_seen_once_lands_on_its_ray_through_a_pinhole(rng):
    """It has no depth, but its one image is data: it goes on the view's ray at
    the cloud's depth, to within working precision (a single Gauss-Newton step
    left it tens of pixels off through a short focal length)."""
    cameras = _cameras("perspective", rng, focal=400.0)
    _, tracks = _tracks(cameras, rng, keep=0.8)
    lone = np.flatnonzero(tracks.point == 5)
    rows = np.setdiff1d(np.arange(len(tracks.view)), lone[1:])  # point 5 kept in one view
    z = tracks.z[rows].copy()
    z[np.flatnonzero(tracks.point[rows] == 5)] += [60.0, -40.0]  # away from the centre's image
    seen_once = bundle.Tracks(tracks.view[rows], tracks.point[rows], z, N, K)
    result = bundle.bundle_adjust(seen_once, "perspective", principal_point=[320.0, 240.0])
    assert not result.placed[5]
    assert np.abs(result.residuals[seen_once.point == 5]).max() < 1e-6


def test_the_levenberg_marquardt_optimum_is_scipys(rng):
    """The Schur-complement solver stops where scipy's least_squares (sparse
    Jacobian, trust-region reflective) does, on noisy views."""
    _, tracks = _tracks(_cameras("scaled", rng), rng, noise=1.0)
    ours = bundle.bundle_adjust(tracks, "scaled")
    cameras = ours.cameras
    n_cam = K * cameras.per_view
    rows = np.arange(2 * len(tracks.view))

    def split(v):
        return v[:3 * N].reshape(N, 3), cameras.with_vector(v[3 * N:])

    def jacobian(v):
        X, cam = split(v)
        d_x, d_view, _ = cam.jacobian_blocks(X, tracks.view, tracks.point)
        cols = np.concatenate([3 * tracks.point[:, None] + np.arange(3),
                               3 * N + cam.per_view * tracks.view[:, None]
                               + np.arange(cam.per_view)], axis=1)
        data = np.concatenate([d_x, d_view], axis=2).reshape(len(rows), -1)
        return csr_matrix((data.ravel(), np.repeat(cols, 2, axis=0).ravel(),
                           np.arange(len(rows) + 1) * cols.shape[1]), shape=(len(rows), 3 * N + n_cam))

    start = np.concatenate([ours.points.ravel(), cameras.vector()])
    perturbed = start + 1e-3 * rng.standard_normal(len(start))
    scipy_fit = least_squares(lambda v: (split(v)[1].project(split(v)[0], tracks.view, tracks.point)
                                         - tracks.z).ravel(), perturbed, jac=jacobian,
                              method="trf", tr_solver="lsmr", x_scale="jac",
                              ftol=1e-15, xtol=1e-15, gtol=1e-15)
    assert np.sqrt(np.mean(np.sum(scipy_fit.fun.reshape(-1, 2) ** 2, 1))) == \
        pytest.approx(ours.rms(), rel=1e-7)


def test_the_metric_upgrade_is_positive_definite_where_the_linear_one_is_not(rng):
    # Affine cameras far from any weak-perspective family: the linear M is indefinite.
    L = rng.standard_normal((5, 3, 2)) * np.array([1.0, 1.0, 20.0])[:, None]
    L[:, 2, 0] *= -1
    A = metric_upgrade_pd(L)
    assert np.all(np.isfinite(A)) and abs(np.linalg.det(A)) > 0
    assert np.linalg.eigvalsh(A @ A.T).min() > 0


def test_bad_options_are_one_line(rng):
    _, tracks = _tracks(_cameras("scaled", rng), rng)
    with pytest.raises(MpeError, match="camera: '.*' is not one of auto, orthographic"):
        bundle.bundle_adjust(tracks, "fisheye")
    with pytest.raises(MpeError, match="loss: '.*' is not one of l2"):
        bundle.bundle_adjust(tracks, "scaled", loss="l1")


def _real_tracks(name):
    import pandas as pd

    frame = pd.read_csv(SHARED / "realdata" / name / "keypoints.csv")
    _, point = np.unique(frame["point"].to_numpy(), return_inverse=True)
    view = frame["view"].to_numpy()
    return bundle.Tracks(view, point, frame[["x", "y"]].to_numpy(float),
                         int(point.max()) + 1, int(view.max()) + 1)


needs_realdata = pytest.mark.skipif(not (SHARED / "realdata" / "house").is_dir(),
                                    reason="../shared/realdata is not beside this checkout")


@needs_realdata
def test_a_run_away_depth_is_said_and_the_pinhole_camera_pins_it():
    """backyard: a hand-held video whose small baseline leaves the depth free
    under weak perspective, but not under a pinhole camera."""
    tracks = _real_tracks("backyard")
    with pytest.warns(DegenerateWarning, match="do not determine the cloud's depth"):
        weak = bundle.bundle_adjust(tracks, "scaled")
    pinhole = bundle.bundle_adjust(tracks, "perspective")
    assert pinhole.converged and bundle.elongation(pinhole.points) < 20
    assert pinhole.rms() < weak.rms()


@needs_realdata
def test_the_model_house_is_rebuilt_within_one_percent_by_a_pinhole_camera():
    import pandas as pd

    tracks = _real_tracks("house")
    truth = pd.read_csv(SHARED / "realdata" / "house" / "gt_points.csv").sort_values("id")
    truth = truth[["x", "y", "z"]].to_numpy()
    orthographic = bundle.bundle_adjust(tracks, "orthographic")
    perspective = bundle.bundle_adjust(tracks, "perspective")
    assert orthographic.converged and perspective.converged
    assert orthographic.rms() < 4.11  # the alternative's 4.10 px, to its printed digits
    diagonal = np.linalg.norm(np.ptp(truth, axis=0))
    size = np.sqrt(np.mean(np.sum((truth - truth.mean(0)) ** 2, 1)))

    def error(X):  # RMS 3D error after a similarity, as a share of the bounding-box diagonal
        return _similarity_error(X, truth) * size / diagonal
    assert error(orthographic.points) < 0.037
    assert error(perspective.points) < 0.01
    assert perspective.rms() < 0.2 * orthographic.rms()


@needs_realdata
def test_on_dino_three_percent_wrong_matches_cost_the_clean_observations_under_ten_percent():
    """Issue 14's target: with 3% of dino's observations swapped for another
    point's in the same view, the fit's error on the observations left clean is
    within 10% of the clean tracks' result (it was 5.9x before the robust start)."""
    clean = _real_tracks("dino")
    rng = np.random.default_rng(1)
    z = clean.z.copy()
    rows = rng.choice(len(z), int(0.03 * len(z)), replace=False)
    for row in rows:
        z[row] = clean.z[rng.choice(np.flatnonzero(clean.view == clean.view[row]))]
    wrong = np.zeros(len(z), dtype=bool)
    wrong[rows] = True
    before = bundle.bundle_adjust(clean)
    after = bundle.bundle_adjust(bundle.Tracks(clean.view, clean.point, z, clean.n_points,
                                               clean.n_views))
    everything = np.ones(len(z), dtype=bool)
    assert after.rms(~wrong) <= 1.1 * before.rms(everything)
    moved = np.linalg.norm(z - clean.z, axis=1) > 5
    assert after.dropped[moved].mean() >= 0.95 and after.converged


def test_a_start_point_behind_a_pinhole_is_pulled_in_front_and_the_rest_left_alone(rng):
    """One start point behind a camera made every perspective start's cost
    infinite (COLMAP's tracks of 250 photos round the chair): it is moved
    towards the centroid until every camera of it sees it at half the centroid's
    depth or more."""
    cameras = affine_cameras("perspective", exp_so3(rng.standard_normal((K, 3)))[:, :2],
                             np.full(K, 2.0), np.zeros((K, 2)), focal=400.0,
                             principal_point=np.zeros(2))
    X, tracks = _tracks(cameras, rng)
    X = 0.2 * (X - X.mean(axis=0))  # well in front of every camera (depth f / s = 200) ...
    R, depth = cameras.current_rotations(), cameras.params[:, 5]
    X[5] = -3.0 * depth[0] * R[0, 2]  # ... but point 5, far behind camera 0, which sees it
    assert np.any((tracks.point == 5) & (tracks.view == 0))
    moved = camera_fits._in_front(X, cameras, tracks)
    seen_at = depth[tracks.view] + np.einsum("ti,ti->t", R[tracks.view, 2], moved[tracks.point])
    assert seen_at.min() >= 0.5 * depth.min() * (1 - 1e-12)
    unchanged = np.ones(len(X), dtype=bool)
    unchanged[5] = False
    assert np.array_equal(moved[unchanged], X[unchanged]) and not np.allclose(moved[5], X[5])


def _distorted_scene(k1, rng, noise=0.5):
    """400 points seen by 5 pinholes of focal 1500 px round 1 rad, with a lens of
    k1 (k2 = 0): the 5-photo set of issue 30, made synthetic."""
    X = rng.uniform(-1, 1, (400, 3)) * [1.0, 0.7, 0.5]
    R = exp_so3(np.c_[0.1 * rng.standard_normal(5), np.linspace(-0.5, 0.5, 5),
                      0.05 * rng.standard_normal(5)])
    cameras = radial_cameras(R, np.c_[np.zeros((5, 2)), np.full(5, 4.0)], 1500.0, [k1, 0.0],
                             (640.0, 480.0))
    view, point = np.repeat(np.arange(5), 400), np.tile(np.arange(400), 5)
    z = cameras.project(X, view, point) + noise * rng.standard_normal((2000, 2))
    return X, bundle.Tracks(view, point, z, 400, 5)


def _median_similarity_error(X, truth):
    a, b = X - X.mean(0), truth - truth.mean(0)
    U, S, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    fitted = (np.sum(S * np.diag(D)) / np.sum(a ** 2)) * a @ (U @ D @ Vt)
    return float(np.median(np.linalg.norm(fitted - b, axis=1)))


def test_the_radial_camera_estimates_a_lens_distortion_the_pinhole_absorbs(rng):
    """Keypoints with k1 = -0.12: the pinhole's cloud bends; the radial camera,
    estimating k1 and k2, comes within 1.2x of the undistorted error."""
    seed = int(rng.integers(1 << 30))
    truth, clean = _distorted_scene(0.0, np.random.default_rng(seed))
    _, distorted = _distorted_scene(-0.12, np.random.default_rng(seed))
    undistorted = _median_similarity_error(
        bundle.bundle_adjust(clean, "perspective", principal_point=(640, 480)).points, truth)
    pinhole = bundle.bundle_adjust(distorted, "perspective", principal_point=(640, 480))
    radial = bundle.bundle_adjust(distorted, "radial", principal_point=(640, 480))
    assert radial.camera == "radial" and radial.converged
    assert _median_similarity_error(radial.points, truth) <= 1.2 * undistorted
    assert _median_similarity_error(pinhole.points, truth) > 1.3 * undistorted
    assert radial.cameras.distortion()[0, 0] == pytest.approx(-0.12, abs=0.05)


def test_a_race_on_a_share_of_many_points_reaches_the_minimum_the_whole_race_reaches(rng, monkeypatch):
    """Over RACE_POINTS placed points the starts race on an even share of
    them and the rest are placed for the winner's cameras: the solve ends at
    the cost the race on all points reaches."""
    from tests.helpers import random_views

    n, k = 1500, 8
    X, _, view, point, z = random_views(rng, "perspective", n, k, turn=0.5, noise=0.5, keep=0.8)
    tracks = bundle.Tracks(view, point, z, n, k)
    raced = camera_fits.race_points(tracks)
    assert raced.sum() == camera_fits.RACE_POINTS and raced[0] and raced[-1]
    assert np.all(np.diff(np.flatnonzero(raced)) <= 2)  # spread over all of them
    shared = bundle.bundle_adjust(tracks, "perspective")
    monkeypatch.setattr(camera_fits, "RACE_POINTS", n)
    whole = bundle.bundle_adjust(tracks, "perspective")
    rms = [np.sqrt(np.mean(np.sum(f.residuals[~f.dropped] ** 2, axis=1))) for f in (shared, whole)]
    assert rms[0] == pytest.approx(rms[1], rel=1e-6)
    assert _similarity_error(shared.points, X) == pytest.approx(_similarity_error(whole.points, X), rel=1e-3)
