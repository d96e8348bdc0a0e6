"""Wrong matches found two views at a time, before any 3D fit."""
import numpy as np
import pandas as pd
import pytest

from mpe3d.solvers.sfm import bundle, stages
from mpe3d.solvers.sfm.epipolar import epipolar_outliers
from mpe3d.solvers.sfm.epipolar_kernels import eight_point_samples, sampson_costs, subspace_costs
from tests.helpers import SHARED, random_views

N, K = 120, 8


def _scene(rng, model="scaled", noise=0.5):
    return random_views(rng, model, N, K, turn=0.6, noise=noise, keep=0.8)[2:]


def _swap(view, z, share, rng):
    """A share of the observations replaced by another point's in the same view, and
    the mask of those that moved."""
    swapped = z.copy()
    for row in rng.choice(len(z), int(share * len(z)), replace=False):
        swapped[row] = z[rng.choice(np.flatnonzero(view == view[row]))]
    return swapped, np.linalg.norm(swapped - z, axis=1) > 0


@pytest.mark.parametrize("model", ["scaled", "perspective"])
def test_wrong_matches_are_flagged_and_right_ones_are_not(model, rng):
    view, point, z = _scene(rng, model)
    clean = epipolar_outliers(view, point, z, K, N)
    if model == "scaled":  # affine views of noisy tracks: nothing is suspected
        assert not clean.any()
    else:  # a pinhole's misfit of the two-view affine test: a few suspicions, all taken back
        assert clean.mean() <= 0.01
        assert not bundle.bundle_adjust(bundle.Tracks(view, point, z, N, K), model).dropped.any()
    corrupted, wrong = _swap(view, z, 0.03, rng)
    far = wrong & (np.linalg.norm(corrupted - z, axis=1) > 20)  # a swap to a near point is no test
    flagged = epipolar_outliers(view, point, corrupted, K, N)
    assert np.sum(flagged & far) >= 0.9 * far.sum()
    assert np.sum(flagged & ~wrong) <= 1


@pytest.mark.parametrize("model", ["scaled", "perspective"])
def test_a_point_seen_twice_whose_views_disagree_is_flagged_in_both(model, rng):
    """No vote can tell which of a two-view track's observations is wrong, but
    the pair's epipolar geometry tells that one is: both are suspects."""
    view, point, z = _scene(rng, model)
    twice = np.flatnonzero(np.bincount(point) >= 3)[:2]
    keep = np.ones(len(point), dtype=bool)
    for p in twice:  # each of the two points kept in its first two views only
        rows = np.flatnonzero(point == p)
        keep[rows[2:]] = False
    view, point, z = view[keep], point[keep], z[keep].copy()
    clean = epipolar_outliers(view, point, z, K, N)
    assert not clean[np.isin(point, twice)].any()
    bad = np.flatnonzero(point == twice[0])
    z[bad[0]] += [0.0, 300.0]
    flagged = epipolar_outliers(view, point, z, K, N)
    assert flagged[bad].all()
    assert not flagged[point == twice[1]].any()


def _real(name):
    """view, point, z of a real data set, sorted by view (skips where it is absent)."""
    path = SHARED / "realdata" / name / "keypoints.csv"
    if not path.exists():
        pytest.skip(f"{path} is absent (the real tracks live beside the repo)")
    frame = pd.read_csv(path).sort_values("view", kind="stable").reset_index(drop=True)
    _, point = np.unique(frame["point"].to_numpy(), return_inverse=True)
    return frame["view"].to_numpy(), point, frame[["x", "y"]].to_numpy(float)


def test_on_dino_with_three_percent_wrong_matches_most_are_flagged_before_the_fit():
    view, point, z = _real("dino")
    corrupted, wrong = _swap(view, z, 0.03, np.random.default_rng(0))
    flagged = epipolar_outliers(view, point, corrupted, view.max() + 1, point.max() + 1)
    assert flagged[wrong].mean() >= 0.9
    assert flagged[~wrong].mean() <= 0.002
    # on the clean tracks a few suspicions (0.1%), which the fit takes back
    tracks = bundle.Tracks(view, point, z, point.max() + 1, view.max() + 1)
    state = stages.BundleState(tracks, stages.BundleOptions())
    stages.suspects(state)
    suspects = state.flagged
    assert suspects.mean() <= 0.002
    assert not bundle.bundle_adjust(tracks).dropped[suspects].any()


def test_on_backyard_wrong_matches_between_views_looking_the_same_way_are_flagged():
    """A hand-held video moving sideways: its views look nearly along one
    direction, so two views' matches lie near a plane of R^4 and a wrong match
    hides in the hyperplane's third direction (35 of 72 found by the hyperplane
    alone) unless that plane is tested too."""
    view, point, z = _real("backyard")
    corrupted, wrong = _swap(view, z, 0.03, np.random.default_rng(0))
    flagged = epipolar_outliers(view, point, corrupted, view.max() + 1, point.max() + 1)
    assert flagged[wrong].mean() >= 0.9
    assert flagged[~wrong].mean() <= 0.002


def test_views_too_far_apart_to_be_paired_flag_nothing(rng):
    view, point, z = _scene(rng)
    few = point < 10  # fewer than MIN_COMMON points shared by any two views
    assert not epipolar_outliers(view[few], point[few], z[few], K, N).any()


def test_the_flags_are_the_same_bits_on_any_number_of_threads(rng):
    """The pairs are tested on threads, each pair's random numbers drawn in the
    pairs' order: stacked small pairs, pairs tested alone (over 256 matches)
    and the fundamental-matrix test all give what one thread gives."""
    from mpe3d.solvers import threads

    n = 400
    view, point, z = random_views(rng, "perspective", n, K, turn=0.6, noise=0.5, keep=0.8)[2:]
    keep = (point < 300) | (view < 3)  # some pairs share over 256 points, some far fewer
    view, point, z = view[keep], point[keep], z[keep]
    corrupted, _ = _swap(view, z, 0.05, rng)
    with threads.limit(1):
        one = epipolar_outliers(view, point, corrupted, K, n)
    with threads.limit(4):
        four = epipolar_outliers(view, point, corrupted, K, n)
    assert one.sum() > 10
    assert np.array_equal(one, four)


def test_the_compiled_msac_scores_are_the_numpy_formulas_to_rounding(rng):
    """sampson_costs against the numpy formulation it replaced (Sampson
    distances of each sample's fundamental matrix, their robust sigma, the
    capped sum), on noisy matches of two pinhole views, a tenth of them wrong."""
    view, _, z = _scene(rng, "perspective", noise=1.0)
    corrupted, _ = _swap(view, z, 0.1, rng)
    q = np.hstack([corrupted[view == 0][:80], corrupted[view == 1][:80]])
    a, b = (np.c_[q[:, cols], np.ones(len(q))] / 500 for cols in (slice(0, 2), slice(2, 4)))
    picks = np.argsort(rng.random((200, len(q))), axis=1)[:, :8]
    rows = (b[picks][..., :, None] * a[picks][..., None, :]).reshape(200, 8, 9)
    F = np.linalg.svd(rows)[2][:, -1].reshape(200, 3, 3)  # eight-point samples, rank 3: no matter
    lines_b, lines_a = a[None] @ np.swapaxes(F, 1, 2), b[None] @ F
    distance = np.abs(np.sum(b * lines_b, axis=2)) / np.sqrt(
        lines_b[..., 0] ** 2 + lines_b[..., 1] ** 2 + lines_a[..., 0] ** 2 + lines_a[..., 1] ** 2)
    sigma = np.maximum(np.median(distance, axis=1) / 0.6745, 1e-12)
    capped = np.minimum(distance / sigma[:, None], 10.0).sum(axis=1)
    got_capped, got_sigma = sampson_costs(F, a, b, 0.6745, 10.0)
    np.testing.assert_allclose(got_sigma, sigma, rtol=1e-12)
    np.testing.assert_allclose(got_capped, capped, rtol=1e-12)
    cost = capped + len(q) * np.log(sigma)
    assert np.argmin(got_capped + len(q) * np.log(got_sigma)) == np.argmin(cost)
    assert len(np.unique(np.round(cost, 6))) > 100  # samples that score differently: a real test


def test_the_compiled_eight_point_samples_are_the_svd_formulation_to_rounding(rng):
    """eight_point_samples against the numpy formulation it replaced: each
    row's 8 smallest keys (argsort), the null vector of their 8 x 9 system
    by a full SVD, the nearest rank-2 matrix; the same matrices up to sign
    and rounding, rank 2, and the same winner of the MSAC scores. A sample
    with a repeated keypoint (a null plane) is reported, and only it; pairs
    of fewer than 8 matches are no error."""
    view, _, z = _scene(rng, "perspective", noise=1.0)
    corrupted, _ = _swap(view, z, 0.1, rng)
    q = np.hstack([corrupted[view == 0][:80], corrupted[view == 1][:80]])
    q[1] = q[0]  # one keypoint matched twice
    a, b = (np.c_[q[:, cols], np.ones(len(q))] / 500 for cols in (slice(0, 2), slice(2, 4)))
    keys = rng.random((200, len(q)))
    keys[:20, :2] = -1.0 - rng.random((20, 2))  # the first 20 samples hold both copies
    picks = np.argsort(keys, axis=1)[:, :8]
    rows = (b[picks][..., :, None] * a[picks][..., None, :]).reshape(200, 8, 9)
    U, S, Vt = np.linalg.svd(np.linalg.svd(rows)[2][:, -1].reshape(200, 3, 3))
    S[:, 2] = 0.0
    expected = U @ (S[..., None] * Vt)
    got, degenerate = eight_point_samples(a, b, keys)
    singular = np.linalg.svd(rows, compute_uv=False)
    assert degenerate[:20].all()  # (a later sample may draw both copies too)
    assert np.array_equal(degenerate, singular[:, 7] < 1e-12 * singular[:, 0])
    sign = np.sign(np.einsum("sij,sij->s", got, expected))[:, None, None]
    np.testing.assert_allclose((sign * got)[~degenerate], expected[~degenerate], atol=1e-12)
    assert np.all(np.abs(np.linalg.det(got)) < 1e-15)  # rank 2
    got[degenerate] = expected[degenerate]  # as the caller recomputes them
    scores = [capped + len(q) * np.log(sigma) for capped, sigma in
              (sampson_costs(F, a, b, 0.6745, 10.0) for F in (got, expected))]
    assert np.argmin(scores[0]) == np.argmin(scores[1])
    short, _ = eight_point_samples(a[:5], b[:5], rng.random((3, 5)))
    assert np.all(np.isfinite(short))


def test_the_compiled_subspace_scores_are_the_numpy_formulas_to_rounding(rng):
    """subspace_costs against the einsum formulation it replaced, on a padded
    stack of three arrays of rows (one of them empty of wrong rows, one short)
    and random 3- and 2-dimensional subspaces of R^4."""
    counts = np.array([60, 23, 41])
    rows = np.zeros((3, 60, 4))
    for b, m in enumerate(counts):
        rows[b, :m] = rng.normal(size=(m, 4)) * [1, 1, 1, 0.01] + (rng.random((m, 1)) < 0.1) * 3
    valid = np.arange(60) < counts[:, None]
    for dim in (3, 2):
        means = rng.normal(size=(3, 50, 4))
        normals = np.linalg.qr(rng.normal(size=(3, 50, 4, 4)))[0][..., :4 - dim].swapaxes(-1, -2).copy()
        along = np.einsum("bnd,bscd->bsnc", rows, normals) - np.einsum("bsd,bscd->bsc", means, normals)[:, :, None]
        distance = np.linalg.norm(along, axis=3)
        median = np.array([[np.median(distance[b, s, :counts[b]]) for s in range(50)] for b in range(3)])
        sigma = np.maximum(median / 0.6745, 1e-12)
        capped = np.where(valid[:, None], np.minimum(distance / sigma[..., None], 10.0), 0).sum(axis=2)
        got_capped, got_sigma = subspace_costs(rows, counts, means, normals, 0.6745, 10.0)
        np.testing.assert_allclose(got_sigma, sigma, rtol=1e-12)
        np.testing.assert_allclose(got_capped, capped, rtol=1e-12)
        assert (np.argmin(got_capped + counts[:, None] * np.log(got_sigma), axis=1)
                == np.argmin(capped + counts[:, None] * np.log(sigma), axis=1)).all()
