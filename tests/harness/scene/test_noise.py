import numpy as np
from scipy.spatial.distance import cdist, pdist

from mpe3d.harness.scene.noise import correspondence_noise, diameter, distance_noise


def test_diameter_matches_brute_force(rng):
    pts = rng.normal(size=(500, 3))
    assert np.isclose(diameter(pts), pdist(pts).max())


def test_distance_noise_rows_and_variance(rng):
    n, q, p, d = 400, 0.25, 0.05, 2.0
    D = np.full((n, n), 100.0)  # far from 0, so clipping never acts
    np.fill_diagonal(D, 0.0)
    noisy = distance_noise(D, q, p, d, rng)
    assert np.allclose(noisy, noisy.T) and np.all(np.diag(noisy) == 0)
    changed = np.abs(noisy - D) > 0
    np.fill_diagonal(changed, False)
    rows = np.flatnonzero(changed.sum(axis=1) > n / 2)
    assert len(rows) == round(q * n)
    # an entry in exactly one noisy row carries variance p d / 4 after symmetrisation
    clean = np.setdiff1d(np.arange(n), rows)
    sample = (noisy - D)[np.ix_(rows, clean)].ravel()
    assert abs(sample.mean()) < 0.01
    assert abs(sample.var() / (p * d / 4) - 1) < 0.05  # ~30k draws: 5% is > 5 sigma
    assert np.all(noisy[np.ix_(clean, clean)] == D[np.ix_(clean, clean)])


def test_distance_noise_clips_negatives(rng):
    D = cdist(*(2 * [rng.uniform(size=(50, 2))]))
    noisy = distance_noise(D, 1.0, 1.0, 1.0, rng)
    assert noisy.min() >= 0.0


def test_correspondence_noise_moves_to_near_points(rng):
    pts = rng.uniform(size=(1000, 3))
    q, p, d = 0.3, 0.1, diameter(pts)  # ~17 expected neighbours within p d
    seen, moved = correspondence_noise(pts, q, p, d, rng)
    changed = np.flatnonzero(np.any(seen != pts, axis=1))
    assert len(changed) == moved and moved <= round(q * 1000)
    assert moved > 0.9 * round(q * 1000)  # nearly every point has a neighbour within p d
    assert np.all(np.linalg.norm(seen[changed] - pts[changed], axis=1) <= p * d + 1e-12)
    # each moved point sits exactly on another sampled point
    assert np.all(cdist(seen[changed], pts).min(axis=1) == 0)


def _observed(**overrides):
    from mpe3d.harness.experiment.config import make_config
    from mpe3d.harness.scene.observe import build_scene, observe, seed_streams

    config = make_config({"shape": "torus", "points": 300, "views": 5, "visibility.k": 3,
                          "observe": "coordinates", "projections": "fixed", **overrides})
    scene = build_scene(config, seed_streams(0))
    obs, facts = observe(scene, config, seed_streams(0))
    return obs, facts


def _views_changed(noisy, clean):
    """(N,) how many views see each point somewhere else than the clean views do."""
    changed = np.zeros(noisy.n_points, dtype=int)
    for a, b in zip(noisy.views, clean.views):
        changed[a.ids] += np.any(a.coordinates != b.coordinates, axis=1)
    return changed


def test_a_wrong_match_is_made_in_exactly_one_view_of_its_point():
    clean, _ = _observed()
    noisy, facts = _observed(**{"noise.type": "correspondence", "noise.fraction": 0.2,
                                "noise.amplitude": 0.1})
    changed = _views_changed(noisy, clean)
    assert changed.max() == 1 and changed.sum() == facts["correspondences_moved"] > 40


def test_noise_views_all_makes_it_in_every_view_that_sees_the_point():
    clean, _ = _observed()
    noisy, facts = _observed(**{"noise.type": "correspondence", "noise.fraction": 0.2,
                                "noise.amplitude": 0.1, "noise.views": "all"})
    changed = _views_changed(noisy, clean)
    assert set(changed[changed > 0]) == {3}  # every point is in exactly 3 views
    assert (changed > 0).sum() == facts["correspondences_moved"]


def test_shared_distance_rows_are_the_same_points_in_every_view():
    def noisy_rows(rows):
        from mpe3d.harness.experiment.config import make_config
        from mpe3d.harness.scene.observe import build_scene, observe, seed_streams

        config = make_config({"shape": "torus", "points": 200, "views": 4, "visibility.k": 3,
                              "noise.type": "distance", "noise.fraction": 0.2,
                              "noise.amplitude": 0.01, "noise.rows": rows})
        scene = build_scene(config, seed_streams(0))
        clean = observe(scene, config.replace(**{"noise.type": "none"}), seed_streams(0))[0]
        noisy = observe(scene, config, seed_streams(0))[0]
        # a noisy row differs from the clean one in nearly every entry, a clean row
        # only where it crosses a noisy one
        return [(set(a.ids[np.mean(a.distances != b.distances, axis=1) > 0.5]), set(a.ids))
                for a, b in zip(noisy.views, clean.views)]
    shared, per_view = noisy_rows("shared"), noisy_rows("per_view")
    union = set.union(*(rows for rows, _ in shared))
    assert 0.15 * 200 <= len(union) <= 0.2 * 200  # round(q N) points, some seen nowhere noisy
    for rows, seen in shared:  # each view's noisy rows: every point of the one set it sees
        assert rows == union & seen
    assert not all(rows == set.union(*(r for r, _ in per_view)) & seen for rows, seen in per_view)
