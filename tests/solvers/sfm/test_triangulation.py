"""Points from known cameras: the linear triangulation and its robust form."""
import numpy as np
import pytest

from mpe3d.solvers.sfm import bundle
from mpe3d.solvers.sfm.triangulation import adjusted_points, dlt_rows, least_squares_points, robust_points
from tests.helpers import random_views

N, K = 40, 6


def _scene(model, rng, noise=0.0):
    X, cameras, view, point, z = random_views(rng, model, N, K, turn=0.5, noise=noise)
    return X, cameras, bundle.Tracks(view, point, z, N, K)


@pytest.mark.parametrize("model", ["orthographic", "scaled", "perspective"])
def test_every_camera_model_triangulates_exactly_from_its_matrices(model, rng):
    X, cameras, tracks = _scene(model, rng)
    A, b = dlt_rows(cameras.projection_matrices(), tracks.view, tracks.z)
    np.testing.assert_allclose(least_squares_points(A, b, tracks.point, N), X, atol=1e-8)


@pytest.mark.parametrize("model", ["scaled", "perspective"])
def test_a_point_that_followed_a_wrong_match_goes_back_to_the_right_ones(model, rng):
    X, cameras, tracks = _scene(model, rng, noise=0.3)
    wrong = np.flatnonzero(tracks.point == 7)[2]
    tracks.z[wrong] += [120.0, -80.0]
    # the point where a least-squares fit over its observations puts it
    mine = tracks.point == 7
    A, b = dlt_rows(cameras.projection_matrices(), tracks.view[mine], tracks.z[mine])
    dragged = X.copy()
    dragged[7] = least_squares_points(A, b, np.zeros(mine.sum(), dtype=int), 1)[0]
    moved, outlying = robust_points(dragged, cameras, tracks, np.array([7]), tau=5.0)
    assert np.linalg.norm(moved[7] - X[7]) < 1.0 < np.linalg.norm(dragged[7] - X[7])
    assert np.flatnonzero(outlying).tolist() == [wrong]
    assert np.array_equal(np.delete(moved, 7, axis=0), np.delete(dragged, 7, axis=0))


def test_a_right_point_stays_near_and_nothing_of_it_is_outlying(rng):
    X, cameras, tracks = _scene("perspective", rng, noise=0.3)
    moved, outlying = robust_points(X, cameras, tracks, np.array([3, 5]), tau=5.0)
    assert np.abs(moved - X).max() < 1.0 and not outlying.any()


def test_observations_that_all_disagree_leave_the_point_alone(rng):
    X, cameras, tracks = _scene("scaled", rng)
    mine = np.flatnonzero(tracks.point == 2)
    tracks.z[mine] += rng.uniform(-400, 400, (len(mine), 2))
    moved, outlying = robust_points(X, cameras, tracks, np.array([2]), tau=1.0)
    assert np.all(np.isfinite(moved)) and outlying[mine].all()


@pytest.mark.parametrize("model", ["scaled", "perspective"])
def test_adjusted_points_reach_their_least_squares_positions_and_no_others_move(model, rng):
    """Points knocked off (one of them far along its depth) go back under the
    fixed cameras, to where the noise-free views put them; the rest stay put."""
    X, cameras, tracks = _scene(model, rng)
    moved = np.zeros(N, dtype=bool)
    moved[[1, 4, 9]] = True
    start = X.copy()
    start[moved] += rng.normal(scale=5.0, size=(3, 3))
    start[9] *= 1.5
    out = adjusted_points(start, cameras, tracks, moved)
    np.testing.assert_allclose(out[moved], X[moved], atol=1e-6)
    assert np.array_equal(out[~moved], start[~moved])
