import numpy as np
import pytest

from mpe3d import solvers
from mpe3d.errors import MpeError
from mpe3d.harness.scene.metrics import roa
from mpe3d.solvers.sgd import align_to_projections, procrustes_restarts, random_projections
from mpe3d.solvers.starts import average_distances, complete_distances
from mpe3d.solvers.stress import project_rows
from tests.helpers import scene_and_observations


def _roa(name, obs, scene, **options):
    rec = solvers.solve(name, obs, random_state=0, **options)
    return roa(rec.points, scene.points), rec


def test_sgd_fixed_noise_free_n256_is_accurate_and_beats_baseline():
    _, scene, obs = scene_and_observations(points=256)
    sgd_roa, rec = _roa("sgd", obs, scene)
    base_roa, _ = _roa("baseline", obs, scene)
    assert sgd_roa < 1e-3
    assert sgd_roa < 0.1 * base_roa
    assert rec.runtime_s > 0 and rec.iterations <= 300
    assert len(rec.stress_history) == rec.iterations + 1


@pytest.mark.parametrize("projections", ["fixed", "variable"])
def test_sgd_improves_on_its_smart_start(projections):
    _, scene, obs = scene_and_observations(points=200, projections=projections, shape="chair")
    start_roa, start = _roa("sgd", obs, scene, max_iter=0)
    end_roa, end = _roa("sgd", obs, scene)
    assert start.iterations == 0
    assert end.stress < 1e-3 * start.stress
    assert end_roa < 0.1 * start_roa
    # the returned iterate is the best one seen, never worse than the start
    assert end.stress == pytest.approx(end.stress_history.min())
    if projections == "variable":
        P = end.projections
        assert np.allclose(P @ np.swapaxes(P, 1, 2), np.eye(2), atol=1e-10)


def test_sgd_minibatch_and_bb_step_converge():
    _, scene, obs = scene_and_observations(points=150)
    assert _roa("sgd", obs, scene, c=0.5)[0] < 1e-2
    assert _roa("sgd", obs, scene, step="bb")[0] < 1e-2


def test_sgd_is_deterministic_given_its_seed():
    _, _, obs = scene_and_observations(points=100, projections="variable")
    a = solvers.solve("sgd", obs, random_state=3, c=0.7, max_iter=20)
    b = solvers.solve("sgd", obs, random_state=3, c=0.7, max_iter=20)
    assert np.array_equal(a.points, b.points)


def test_random_start_is_in_the_unit_cube():
    _, _, obs = scene_and_observations(points=100)
    rec = solvers.solve("sgd", obs, init="random", random_state=0, max_iter=0)
    assert rec.points.min() >= 0 and rec.points.max() <= 1


def test_baseline_averages_only_views_that_see_both_points():
    _, scene, obs = scene_and_observations(points=60, views=5)
    D, count = average_distances(obs)
    i, j = 3, 17
    seen = [k for k, v in enumerate(obs.views) if i in v.ids and j in v.ids]
    assert count[i, j] == len(seen)
    values = [obs.views[k].distances[list(obs.views[k].ids).index(i), list(obs.views[k].ids).index(j)]
              for k in seen]
    assert D[i, j] == pytest.approx(np.mean(values))


def test_baseline_average_is_numpys_per_view_sums_bit_for_bit():
    # the compiled row-by-row sums must add the views in their order, as the
    # np.ix_ updates did: the baseline's and every smart start's bits hang on it
    _, _, obs = scene_and_observations(points=300, views=6, projections="variable",
                                          **{"noise.type": "distance", "noise.fraction": 0.5})
    N = obs.n_points
    total, count = np.zeros((N, N)), np.zeros((N, N), dtype=np.int32)
    for view in obs.views:
        total[np.ix_(view.ids, view.ids)] += view.distance_matrix()
        count[np.ix_(view.ids, view.ids)] += 1
    total[count > 0] /= count[count > 0]
    D, seen = average_distances(obs)
    assert np.array_equal(seen, count) and (count > 1).any() and (count == 0).any()
    assert np.array_equal(D, total)


def test_the_authors_baseline_averages_over_all_views_with_zeros_for_unseen_pairs():
    from mpe3d.solvers.starts import authors_average

    _, scene, obs = scene_and_observations(points=60, views=5)
    D = authors_average(obs)
    i, j = 3, 17
    values = [v.distances[list(v.ids).index(i), list(v.ids).index(j)]
              for v in obs.views if i in v.ids and j in v.ids]
    assert 0 < len(values) < 5  # seen by some views only: the zeros count
    assert D[i, j] == pytest.approx(np.sum(values) / 5)
    never = average_distances(obs)[1] == 0
    assert np.all(D[never] == 0)
    ours = solvers.solve("baseline", obs, random_state=0).points
    theirs = solvers.solve("baseline", obs, random_state=0, method="authors").points
    assert not np.allclose(ours, theirs)


def test_pairs_never_seen_get_graph_distances():
    # a path 0-1-2: pair (0, 2) is never seen and gets 1 + 2 = 3
    D = np.array([[0, 1, 0], [1, 0, 2], [0, 2, 0]], dtype=float)
    seen = D > 0
    out = complete_distances(D, seen)
    assert out[0, 2] == out[2, 0] == 3.0


def test_align_to_projections_recovers_the_frame(rng):
    P = random_projections(5, rng)
    Q = project_rows(rng.standard_normal((3, 3)))
    R2 = project_rows(rng.standard_normal((5, 2, 2)))  # unknown O(2) per view
    found = align_to_projections(R2 @ P @ Q, P, rng)
    # P @ found must equal P @ Q up to each view's O(2)
    PQ, Pf = P @ Q, P @ found
    assert np.allclose(np.swapaxes(PQ, 1, 2) @ PQ, np.swapaxes(Pf, 1, 2) @ Pf, atol=1e-8)



def _one_start(P_fit, P, Q, sweeps):
    """The alternation for one start, as it ran before the starts were batched."""
    err = np.inf
    for _ in range(sweeps):
        R = project_rows(P_fit @ np.swapaxes(P @ Q, 1, 2))
        Q = project_rows(np.einsum("kai,kab,kbj->ij", P, np.swapaxes(R, 1, 2), P_fit))
        previous, err = err, float(np.sum((P_fit - R @ P @ Q) ** 2))
        if previous - err < 1e-15:
            break
    return Q, err


@pytest.mark.parametrize("views, noise", [(2, 0.0), (5, 0.05), (9, 0.3), (20, 0.1)])
def test_batched_procrustes_restarts_are_each_start_alone(views, noise):
    """Every start's last Q and error, the same bits as one start at a time
    (some starts stop after a few sweeps, others run all of them)."""
    rng = np.random.default_rng(views)
    P = random_projections(views, rng)
    R2 = project_rows(rng.standard_normal((views, 2, 2)))
    P_fit = project_rows(R2 @ P @ project_rows(rng.standard_normal((3, 3)))
                         + noise * rng.standard_normal((views, 2, 3)))
    draws = np.random.default_rng(1)
    starts = np.concatenate([np.eye(3)[None], project_rows(draws.standard_normal((11, 3, 3)))])
    Q, err = procrustes_restarts(P_fit, P, starts, sweeps=120)
    alone = [_one_start(P_fit, P, start, 120) for start in starts]
    np.testing.assert_array_equal(Q, np.array([q for q, _ in alone]))
    np.testing.assert_array_equal(err, np.array([e for _, e in alone]))
    # align_to_projections draws these starts from the same seed and keeps the first best
    found = align_to_projections(P_fit, P, np.random.default_rng(1), restarts=12, sweeps=120)
    np.testing.assert_array_equal(found, alone[int(np.argmin(err))][0])

@pytest.mark.parametrize("options, message", [
    ({"step": "adam"}, "solver.step"), ({"c": 0.0}, "solver.c"), ({"max_iter": -1}, "solver.max_iter"),
])
def test_bad_solver_options(options, message):
    _, _, obs = scene_and_observations(points=30)
    with pytest.raises(MpeError, match=message):
        solvers.solve("sgd", obs, **options)


def test_bad_observations_are_rejected():
    _, _, obs = scene_and_observations(points=30)
    view = obs.views[0]
    D = view.distances.copy()
    D[0, 1] = np.nan
    broken = solvers.Observations(obs.n_points, (solvers.View(view.ids, D),) + obs.views[1:],
                                  obs.projections)
    with pytest.raises(MpeError, match="view 0: distance matrix holds NaN"):
        solvers.solve("sgd", broken)
    short = solvers.Observations(obs.n_points, (solvers.View(view.ids, D[:3, :3]),) + obs.views[1:])
    with pytest.raises(MpeError, match="view 0: distance matrix has shape"):
        solvers.solve("baseline", short)
    twice = view.ids.copy()
    twice[1] = twice[0]
    repeated = solvers.Observations(obs.n_points, (solvers.View(twice, view.distances),) + obs.views[1:])
    with pytest.raises(MpeError, match="view 0: a point id appears twice"):
        solvers.solve("sgd", repeated)


def test_sgd_on_views_sharing_no_point_ends_finite():
    # Each point in 1 of 8 views: the variable-setting stress is flat in places,
    # and the adaptive step once overflowed into NaN projections (a full-scale
    # reproduce-paper run failed with "SVD did not converge").
    config, scene, obs = scene_and_observations(shape="airplane", points=512, views=8,
                                                projections="variable", **{"visibility.k": 1})
    from mpe3d.harness.scene.observe import seed_streams

    rec = solvers.solve("sgd", obs, random_state=seed_streams(config["seed"])["solver"])
    assert np.all(np.isfinite(rec.points)) and np.all(np.isfinite(rec.projections))
    assert np.isfinite(rec.stress)
