"""The compiled kernels and the batched linear algebra behind the speed-ups
(issue 16), each against the plain formulation it replaces."""
import warnings
from pathlib import Path

import numpy as np
import pytest

from mpe3d.solvers import kernels, point_kernels, warmup
from mpe3d.solvers.linalg import gram_by_group, matvec_by_group, pinv_psd, rows_by_group
from mpe3d.solvers.sfm import epipolar_kernels
from mpe3d.solvers.sfm import kernels as sfm_kernels
from tests.helpers import blas_fuses_small_products


def test_smacof_takes_scikit_learns_steps(rng):
    """The baseline's MDS: scikit-learn's metric SMACOF, iterate for iterate."""
    from sklearn.manifold import smacof

    truth = rng.normal(size=(120, 3))
    D = np.linalg.norm(truth[:, None] - truth[None], axis=2)
    D = D * (1 + 0.05 * np.abs(rng.normal(size=D.shape)))
    D = np.triu(D, 1) + np.triu(D, 1).T  # a noisy, non-Euclidean matrix: many iterations
    start = rng.normal(size=(120, 3))
    for max_iter in (1, 5, 300):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            want, stress, steps = smacof(D, metric=True, n_components=3, init=start, n_init=1,
                                         max_iter=max_iter, normalized_stress=False,
                                         return_n_iter=True)
        got, got_stress, got_steps = kernels.smacof(D, start, max_iter=max_iter)
        assert got_steps == steps
        assert np.allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
        assert got_stress == pytest.approx(stress, rel=1e-9)
    assert steps > 5  # the stopping rule was reached, not the cap


def test_smacof_refuses_another_dimension(rng):
    with pytest.raises(ValueError, match="3D"):
        kernels.smacof(np.ones((4, 4)), rng.normal(size=(4, 2)))


def _gauss_newton(x, P, Y, d, root, steps):
    """Refine's former NumPy placement of one point, for reference."""
    for _ in range(steps):
        diff = np.einsum("nij,j->ni", P, x) - Y
        e = np.maximum(np.linalg.norm(diff, axis=1), 1e-12)
        J = -np.einsum("ni,nij->nj", diff / e[:, None], P)
        step = np.linalg.lstsq(root[:, None] * J, -root * (d - e), rcond=None)[0]
        x = x + step
        if np.linalg.norm(step) <= 1e-9 * (1.0 + np.linalg.norm(x)):
            break
    return x


def test_multilateration_matches_numpy_gauss_newton(rng):
    from mpe3d.solvers.sgd import random_projections

    point = rng.normal(size=3)
    P = np.repeat(random_projections(3, rng), 40, axis=0)
    anchors = rng.normal(size=(120, 3))
    Y = np.einsum("nij,nj->ni", P, anchors)
    d = np.linalg.norm(np.einsum("nij,j->ni", P, point) - Y, axis=1) + 0.01 * rng.normal(size=120)
    root = rng.uniform(0.5, 2.0, size=120)
    start = point + 0.3 * rng.normal(size=3)
    got = point_kernels._multilaterate(start, P, Y, d, root, 10)
    assert np.allclose(got, _gauss_newton(start, P, Y, d, root, 10), atol=1e-12)
    starts = np.array([0, 40, 80, 120])
    misfit = np.abs(d - np.linalg.norm(np.einsum("nij,j->ni", P, got) - Y, axis=1))
    want = [np.median(misfit[a:b]) for a, b in zip(starts[:-1], starts[1:])]
    assert np.allclose(point_kernels.row_misfits(got, P, Y, d, starts), want, rtol=1e-14)


def test_multilateration_in_one_view_falls_back_to_least_squares(rng):
    """Anchors in one view leave the point's depth open: the normal equations
    are singular, and the step must be gelsd's minimum-norm one, as before."""
    from mpe3d.solvers.sgd import random_projections

    P = np.repeat(random_projections(1, rng), 50, axis=0)
    anchors = rng.normal(size=(50, 3))
    Y = np.einsum("nij,nj->ni", P, anchors)
    point = rng.normal(size=3)
    d = np.linalg.norm(np.einsum("nij,j->ni", P, point) - Y, axis=1)
    start = point + 0.2 * rng.normal(size=3)
    root = np.ones(50)
    got = point_kernels._multilaterate(start, P, Y, d, root, 10)
    assert np.allclose(got, _gauss_newton(start, P, Y, d, root, 10), atol=1e-10)


def test_pairwise_sum_is_numpys_sum_to_the_bit(rng):
    for n in (0, 1, 5, 7, 8, 9, 16, 17, 127, 128, 129, 300, 1000):
        for _ in range(20):
            a = rng.random(n) * 10.0 ** rng.integers(-6, 6, n)
            assert point_kernels.pairwise_sum(a) == np.sum(a), n


def _placed_by_numpy(x, P, Y, d, starts, line, sigmas, scouts, reweights, steps):
    """Refine's former placement of a weak point (a Python loop over the pairs
    of its rows around the compiled multilateration), for reference."""
    rows = [(P[a:b], Y[a:b], d[a:b]) for a, b in zip(starts[:-1], starts[1:])]

    def stack(parts):
        sizes = [len(part[2]) for part in parts]
        return (np.ascontiguousarray(np.concatenate([p[0] for p in parts])),
                np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts]),
                np.concatenate([[0], np.cumsum(sizes)]))

    def placed(x, stacked, weights=None):
        P, Y, d, starts = stacked
        root = np.ones(len(d)) if weights is None else np.repeat(np.sqrt(weights), np.diff(starts))
        return point_kernels._multilaterate(x, P, Y, d, root, steps)

    scout_rows = [tuple(a[::-(-len(r[2]) // scouts)] for a in r) for r in rows]
    few = stack(scout_rows)
    best, best_cost = x, np.inf
    for a in range(len(rows)):
        for b in range(a + 1, len(rows)):
            point = placed(x, stack([scout_rows[a], scout_rows[b]]))
            cost = np.minimum(point_kernels.row_misfits(point, *few), line).sum()
            if cost < best_cost:
                best, best_cost = point, cost
    every = stack(rows)
    for last in range(reweights, 0, -1):
        using = every if last == 1 else few
        best = placed(best, using, 1.0 / np.maximum(point_kernels.row_misfits(best, *using), line / sigmas) ** 2)
    return best


@pytest.mark.parametrize("n_rows", [2, 3, 9])
def test_placing_a_point_in_one_call_is_the_numpy_loop_to_the_bit(rng, n_rows):
    from mpe3d.solvers.sgd import random_projections

    sizes = rng.integers(1, 200, size=n_rows)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    P = np.ascontiguousarray(np.repeat(random_projections(n_rows, rng), sizes, axis=0))
    point = rng.normal(size=3)
    Y = np.einsum("nij,nj->ni", P, rng.normal(size=(starts[-1], 3)))
    d = np.linalg.norm(np.einsum("nij,j->ni", P, point) - Y, axis=1) + 0.01 * rng.normal(size=starts[-1])
    d[starts[1]:starts[2]] *= 1.5  # a corrupted row
    for start in (point + 0.3 * rng.normal(size=3), rng.normal(size=3)):
        args = (start, P, Y, d, starts, 0.05, 5.0, 64, 3, 10)
        assert np.array_equal(point_kernels.place_point(*args), _placed_by_numpy(*args))


def test_pinv_psd_is_pinv_on_good_and_degenerate_systems(rng):
    A = rng.normal(size=(500, 4, 3))
    M = np.einsum("nai,naj->nij", A, A)
    M[:100] = np.einsum("nai,naj->nij", A[:100, :2], A[:100, :2])  # rank 2: a point in one view
    M[100:110] = 0.0  # no observation at all
    M[110:120] *= np.array([1.0, 1.0, 1e-12])  # nearly singular along one axis
    got, want = pinv_psd(M), np.linalg.pinv(M)
    assert np.allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
    good = np.einsum("nai,naj->nij", A, A)[120:]
    assert np.allclose(pinv_psd(good), np.linalg.pinv(good), rtol=1e-9, atol=1e-12)


def test_grouped_products_equal_the_per_row_ones(rng):
    group = rng.integers(0, 5, size=300)
    group[group == 3] = 4  # a group with no rows
    M = rng.normal(size=(5, 2, 3))
    Y = rng.normal(size=(300, 3))
    assert np.allclose(matvec_by_group(M, group, Y), np.einsum("tij,tj->ti", M[group], Y))
    A, B = rng.normal(size=(300, 2, 4)), rng.normal(size=(300, 2, 3))
    want = np.zeros((5, 4, 3))
    np.add.at(want, group, np.einsum("tai,taj->tij", A, B))
    assert np.allclose(gram_by_group(A, group, 5, B), want)
    assert np.allclose(gram_by_group(Y, group, 5), [Y[group == g].T @ Y[group == g] for g in range(5)])
    # rows in increasing order, as a scan finds them; rows of groups past n_groups in none
    assert all(np.array_equal(rows, np.flatnonzero(group == g)) for g, rows in enumerate(rows_by_group(group, 4)))
    assert len(rows_by_group(group, 4)) == 4 and rows_by_group(group, 0) == []


@pytest.mark.parametrize("per_view", [4, 6])  # 6 has a loop of its own
def test_the_reduced_system_subtracts_the_sparse_stack_s_gram_matrix(rng, per_view, monkeypatch):
    """S = V - Y^T Y for Y stacking each point's 3 rows over its observations'
    camera columns; a shared column (a lens for all views) recurs in a row, and
    a point seen twice in one view (a conflicting track) meets itself there.
    Split by views among threads, it is the same bits."""
    n_points, n_views = 30, 6
    point = np.sort(rng.integers(0, n_points, size=120))
    view = rng.integers(0, n_views, size=120)  # in any order within a point, repeats too
    assert any(len(set(view[point == i])) < np.sum(point == i) for i in range(n_points))
    cols = np.c_[per_view * view[:, None] + np.arange(per_view), np.full(120, n_views * per_view)]
    size = n_views * per_view + 1
    Y = rng.normal(size=(120, 3, per_view + 1))
    dense = np.zeros((3 * n_points, size))
    for t in range(120):
        for a in range(3):
            np.add.at(dense[3 * point[t] + a], cols[t], Y[t, a])
    starts = np.concatenate([[0], np.cumsum(np.bincount(point, minlength=n_points))])
    V = rng.normal(size=(size, size))
    S = sfm_kernels.reduced_system(V, Y, view, starts, np.full((n_views, n_views, per_view, per_view), np.nan))
    upper = np.triu_indices(size)
    assert np.allclose(S[upper], (V - dense.T @ dense)[upper], rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.tril(S, -1), np.tril(V, -1))  # Cholesky reads the upper triangle only
    monkeypatch.setattr(sfm_kernels, "_THREADED_PAIRS", 0)  # threads however small the system
    for threads in (2, 3, 8):
        assert np.array_equal(sfm_kernels.reduced_system(V, Y, view, starts, np.full(
            (n_views, n_views, per_view, per_view), np.nan), threads), S)
    # the compiled loops index unchecked: a V that does not fit is refused, not written past
    # (kernels.warm() once passed a 2 x 2 V for a 3 x 3 system, and the heap it corrupted
    # crashed sweep workers in the garbage collector, at random)
    with pytest.raises(ValueError, match="do not fit"):
        sfm_kernels.reduced_system(np.eye(size - 1), Y, view, starts,
                               np.empty((n_views, n_views, per_view, per_view)))


def test_the_transposed_products_are_numpy_s_stacked_products(rng):
    """A[t]^T B[t], the same bits as numpy's stacked matmul of the transposed
    view where its BLAS chains fused multiply-adds, else to rounding."""
    A, B = rng.normal(size=(200, 2, 3)), rng.normal(size=(200, 2, 7))
    for right in (A, B):
        got = sfm_kernels.transposed_products(A, right)
        expected = A.transpose(0, 2, 1) @ right
        if blas_fuses_small_products():
            assert np.array_equal(got, expected)
        else:
            np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("c", [6, 7])
def test_the_whitened_blocks_are_numpy_s_stacked_products(rng, c):
    """Y[t] = root[point[t]] @ W[rows[t]], the same bits as numpy's stacked
    matmul where its BLAS chains fused multiply-adds, else to rounding."""
    root, W = rng.normal(size=(30, 3, 3)), rng.normal(size=(200, 3, c))
    point, rows = rng.integers(0, 30, size=200), rng.permutation(200)
    got = sfm_kernels.whitened_blocks(root, W, point, rows)
    expected = np.matmul(root[point], W[rows])
    if blas_fuses_small_products():
        assert np.array_equal(got, expected)
    else:
        np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)


def test_a_robust_losss_kernel_is_warmed_only_for_a_solve_that_asks_for_it():
    """A first compile skips the robust losses' dense kernels (a third of it)
    unless a solve uses one; that solve still compiles it before its clock."""
    import subprocess
    import sys

    code = """
from mpe3d import solvers
from mpe3d.solvers import kernels, warmup
from tests.helpers import scene_and_observations
warmup.warm()
print(len(kernels.DENSE_KERNELS[kernels.L2].signatures), len(kernels.DENSE_KERNELS[kernels.HUBER].signatures))
_, _, obs = scene_and_observations(points=40, views=3, projections="fixed", **{"noise.type": "distance",
                                   "noise.fraction": 0.3, "noise.amplitude": 0.05})
solvers.solve("refine", obs, random_state=0, loss="huber")
print(len(kernels.DENSE_KERNELS[kernels.HUBER].signatures), len(kernels.DENSE_KERNELS[kernels.SOFT_L1].signatures))
"""
    from tests.helpers import REPO

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "0", "1", "0"], out.stdout


def test_the_fixed_elimination_is_the_same_in_blocks(monkeypatch):
    """factorize's fixed setting forms X = Y(h) block by block of points (no
    N x 3 x 4K array at a million points); the block size changes no digit
    that matters."""
    from mpe3d import solvers
    from mpe3d.harness.scene.metrics import roa
    from mpe3d.solvers import factorize
    from tests.helpers import scene_and_observations

    _, scene, obs = scene_and_observations(points=400, views=5, projections="fixed")
    whole = solvers.solve("factorize", obs, random_state=0).points
    monkeypatch.setattr(factorize, "_POINT_BLOCK", 64)  # seven blocks, the last one short
    blocks = solvers.solve("factorize", obs, random_state=0).points
    assert np.allclose(blocks, whole, atol=1e-12)
    assert roa(blocks, scene.points) < 1e-12


def test_stresses_of_the_same_observations_share_their_inputs():
    """A solve and its report build several Stress objects of one set of views:
    the distance matrices and sparse pair sets are made once."""
    from mpe3d.solvers.stress import Stress
    from tests.helpers import scene_and_observations

    _, _, obs = scene_and_observations(points=60, observe="coordinates")
    first, second = Stress(obs), Stress(obs, "huber", 0.1)
    assert all(a is b for a, b in zip(first.D, second.D))


def test_compiled_median_is_numpys(rng):
    """Odd and even counts, ties and all-equal rows: the rejection line
    compares misfits with it, so it must be numpy's to the bit."""
    from mpe3d.solvers.point_kernels import median_in_place

    for m in [*range(1, 30), 200, 201, 620, 621, 3000]:
        for values in (rng.normal(size=m), rng.integers(0, 3, size=m).astype(float), np.ones(m),
                       np.where(rng.random(m) < 0.2, np.inf, np.abs(rng.normal(size=m))),
                       np.sort(rng.normal(size=m)), np.sort(rng.normal(size=m))[::-1].copy()):
            assert median_in_place(values.copy()) == np.median(values)


def test_row_residuals_compiled_match_numpy(rng):
    from mpe3d import make_config
    from mpe3d.harness.scene.observe import build_scene, observe, seed_streams
    from mpe3d.solvers.sgd import random_projections
    from mpe3d.solvers.stress import Stress

    config = make_config({"shape": "chair", "points": 200, "views": 4, "visibility.mode": "exact",
                          "visibility.k": 3, "projections": "variable"})
    streams = seed_streams(0)
    scene = build_scene(config, streams)
    obs, _ = observe(scene, config, streams)
    X = scene.points + 0.01 * rng.normal(size=scene.points.shape)
    P = random_projections(4, rng)
    among = [rng.random(v.size) < 0.8 for v in obs.views]
    got = Stress(obs).row_residuals(X, P, among)
    want = Stress(obs, kernel="numpy").row_residuals(X, P, among)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))


def _numpy_affine_als(view, point, z, X, N, K, max_iter, tol, floor):
    """The alternating sweeps as first written in NumPy, from X: the reference."""
    from mpe3d.solvers.linalg import fit_views

    informative = np.bincount(point, minlength=N)[point] >= 2
    previous = float(np.finfo(float).max)
    for sweep in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        L, t = fit_views(X, view, point, z, K, informative)
        lhs = np.zeros((N, 3, 3))
        rhs = np.zeros((N, 3))
        np.add.at(lhs, point, np.einsum("tab,tcb->tac", L[view], L[view]))
        np.add.at(rhs, point, np.einsum("tab,tb->ta", L[view], z - t[view]))
        X = np.einsum("nij,nj->ni", pinv_psd(lhs), rhs)
        rms = float(np.sqrt(np.mean((np.einsum("tab,ta->tb", L[view], X[point]) + t[view] - z) ** 2)))
        if previous - rms <= tol * previous or rms <= floor:
            break
        previous = rms
    return X, L, rms, sweep


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_compiled_affine_sweeps_are_the_numpy_ones(rng, noise):
    N, K = 80, 5
    X = rng.normal(size=(N, 3))
    L, t = rng.normal(size=(K, 3, 2)), rng.normal(size=(K, 2))
    seen = rng.random((K, N)) < 0.7
    seen[:2, :40] = True
    seen[:, 70] = [True, False, False, False, False]  # seen once: rank-2 normal equations
    seen[:, 71] = False  # never seen: comes back at the origin
    seen[4] = False
    seen[4, :2] = True  # a view of two points: its 4 x 4 system has rank 2
    view, point = np.nonzero(seen)
    z = np.einsum("tab,ta->tb", L[view], X[point]) + t[view] + noise * rng.normal(size=(len(view), 2))
    start = X + 0.3 * rng.normal(size=X.shape)  # the sweeps' own start, away from the answer
    got = point_kernels.affine_als(view, point, z, start, np.bincount(point, minlength=N)[point] >= 2,
                             K, 300, 1e-13, 1e-14)
    want = _numpy_affine_als(view, point, z, start, N, K, 300, 1e-13, 1e-14)
    assert got[3] == want[3]
    assert got[2] == pytest.approx(want[2], rel=1e-9, abs=1e-15)
    assert np.allclose(got[0], want[0], rtol=1e-7, atol=1e-7 * np.abs(want[0]).max())
    assert np.allclose(got[1], want[1], rtol=1e-7, atol=1e-9)
    assert np.all(got[0][71] == 0.0)


@pytest.mark.parametrize("parts", [2, 3, 4])
def test_warm_in_parts_calls_every_warm_up_once(monkeypatch, parts):
    """The shares of ``warm(part=, parts=)`` are disjoint and together compile
    every registered kernel of every loss: no kernel is left for the suite's
    workers to compile, nor compiled twice side by side."""
    import dataclasses

    calls = []
    everything = {name: dataclasses.replace(step, call=lambda name=name: calls.append(name))
                  for name, step in warmup.registered().items()}
    monkeypatch.setattr(warmup, "_REGISTRY", everything)
    # the stress and SfM kernels are registered when their modules are imported
    for module in KERNEL_MODULES:
        assert any(name.startswith(module.__name__ + ".") for name in everything), module
    shares = []
    for part in range(parts):
        calls.clear()
        warmup.warm(part=part, parts=parts)
        shares.append(list(calls))
    assert all(shares)  # every process has something to compile
    assert sorted(c for share in shares for c in share) == sorted(everything)
    with pytest.raises(ValueError, match="part must be in"):
        warmup.warm(part=parts, parts=parts)


def test_a_solve_warms_only_its_loss(monkeypatch):
    """``warm(loss)`` calls the warm-ups of every loss-free kernel and of
    ``loss``'s own, each once per process."""
    import dataclasses

    calls = []
    everything = {name: dataclasses.replace(step, call=lambda name=name: calls.append(name))
                  for name, step in warmup.registered().items()}
    monkeypatch.setattr(warmup, "_REGISTRY", everything)
    monkeypatch.setattr(warmup, "_DONE", set())
    warmup.warm("huber")
    warmup.warm("huber")
    assert sorted(calls) == sorted(n for n, w in everything.items() if w.loss in (None, "huber"))
    assert warmup.warmed("huber") and not warmup.warmed("soft_l1")



def test_a_warm_in_the_background_is_waited_for_and_its_failure_raised_again(monkeypatch):
    """A warm() in the solve's thread waits for one started in the background
    (each warm-up runs once); a warm-up that failed there raises in the
    caller's thread when tried again."""
    import dataclasses
    import threading

    calls, gate = [], threading.Event()

    def slow(name):
        gate.wait(5)
        calls.append(name)

    everything = {name: dataclasses.replace(step, call=lambda name=name: slow(name))
                  for name, step in warmup.registered().items()}
    monkeypatch.setattr(warmup, "_REGISTRY", everything)
    monkeypatch.setattr(warmup, "_DONE", set())
    thread = warmup.warm_in_background("l2")
    waiter = threading.Thread(target=warmup.warm, args=("l2",))
    waiter.start()
    gate.set()
    thread.join(10)
    waiter.join(10)
    assert sorted(calls) == sorted(n for n, w in everything.items() if w.loss in (None, "l2"))

    def broken():
        raise RuntimeError("no cache")

    first = next(n for n, w in everything.items() if w.loss is None)
    monkeypatch.setattr(warmup, "_REGISTRY", {first: dataclasses.replace(everything[first], call=broken)})
    monkeypatch.setattr(warmup, "_DONE", set())
    warmup.warm_in_background("l2").join(10)
    assert not warmup.warmed("l2")
    with pytest.raises(RuntimeError, match="no cache"):
        warmup.warm("l2")


KERNEL_MODULES = (kernels, point_kernels, sfm_kernels, epipolar_kernels)


def _references(modules) -> tuple[set[str], dict[str, set[str]]]:
    """The compiled kernels (``@njit``) of ``modules``, and what each top-level
    function or constant names in its body: a kernel calls another by name,
    or picks one from a table (``DENSE_KERNELS``)."""
    import ast
    import inspect

    compiled, names = set(), {}
    for module in modules:
        for node in ast.parse(inspect.getsource(module)).body:
            if isinstance(node, ast.FunctionDef):
                key = node.name
                if any("njit" in ast.unparse(d) for d in node.decorator_list):
                    compiled.add(key)
            elif isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
                key = node.targets[0].id
            else:
                continue
            body = node.body if isinstance(node, ast.FunctionDef) else [node.value]
            names[key] = {n.id for part in body for n in ast.walk(part) if isinstance(n, ast.Name)}
    return compiled, names


def test_every_compiled_kernel_has_its_warm_up():
    """Every compiled kernel of the solvers is compiled by a warm-up: it has
    its own entry where it is defined (``@warm_up``), or a kernel with one
    calls it. Read off the source, so numba's cache cannot hide a kernel.
    A kernel added without a warm-up fails here."""
    import pkgutil

    import mpe3d.solvers as package

    modules = [__import__(info.name, fromlist=["_"])
               for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
    with_kernels = [m for m in modules if "@njit" in Path(m.__file__).read_text()]
    assert set(with_kernels) == set(KERNEL_MODULES), with_kernels  # kernels live in these only
    compiled, names = _references(with_kernels)
    reached = set()
    todo = [name.removeprefix(module.__name__ + ".").split(".")[0]
            for name in warmup.registered() for module in KERNEL_MODULES
            if name.startswith(module.__name__ + ".")]
    while todo:
        name = todo.pop()
        if name not in reached:
            reached.add(name)
            todo.extend(names.get(name, ()))
    assert compiled <= reached, sorted(compiled - reached)
