"""A plug-in file as a user writes one: a solver and a dataset, outside mpe3d.

The solver is classical MDS of the views' averaged distances (unseen pairs
get the mean), with each free projection fitted by Procrustes; the dataset is
two or three round blobs. The tests load it with ``--plugin``, edit it, and
break it on purpose.
"""
import numpy as np

import mpe3d
from mpe3d import Interval, Reconstruction


@mpe3d.register_solver("avgmds", constraints={"jitter": Interval(float, 0, None)},
                       summary="classical MDS of the averaged distances (a test plug-in)")
def avgmds(observations, *, random_state, jitter: float = 0.0):
    n = observations.n_points
    total, count = np.zeros((n, n)), np.zeros((n, n))
    for view in observations.views:
        pairs = np.ix_(view.ids, view.ids)
        total[pairs] += view.distance_matrix()
        count[pairs] += 1
    D = np.where(count > 0, total / np.maximum(count, 1), np.mean(total[count > 0]))
    np.fill_diagonal(D, 0.0)
    J = np.eye(n) - 1.0 / n
    w, V = np.linalg.eigh(-0.5 * J @ D**2 @ J)
    X = V[:, -3:] * np.sqrt(np.maximum(w[-3:], 0.0)) + jitter * random_state.standard_normal((n, 3))
    if observations.fixed:
        P = observations.projections
    else:
        P = []
        for view in observations.views:
            A = X[view.ids] - X[view.ids].mean(axis=0)
            U, _, Vt = np.linalg.svd(view.image().T @ A, full_matrices=False)
            P.append(U @ Vt)
        P = np.array(P)
    return Reconstruction(points=X, projections=P, stress=None, stress_history=np.array([0.0]),
                          iterations=0, termination="closed form")


@mpe3d.register_dataset("blobs", items=("two", "three"), summary="round blobs (a test plug-in)")
def blobs(item, *, n_points, random_state):
    count = {"two": 2, "three": 3}[item]
    directions = random_state.standard_normal((n_points, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return 2.0 * np.eye(3)[np.arange(n_points) % count] + 0.6 * directions
