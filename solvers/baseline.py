"""The paper's baseline: MDS on the average of the per-view distance matrices.

Paper, Section "Baseline Approach": average the K pairwise distance matrices and
embed the result in 3D with MDS. The same embedding is 3DMPE's "smart"
initialisation.
"""

from __future__ import annotations

import numpy as np

from mpe3d.solvers.base import Choice, Interval, Observations, Reconstruction, register_solver
from mpe3d.solvers.starts import fit_projections, mds_embedding
from mpe3d.solvers.stress import Stress

_PARAMETER_CONSTRAINTS = {
    "method": Choice(("smacof", "classical", "authors")),
    "max_iter": Interval(int, 1, None),
}


@register_solver("baseline", constraints=_PARAMETER_CONSTRAINTS, paper=True,
          summary="the paper's baseline: MDS of the completed distance matrix")
def solve_baseline(observations: Observations, *, random_state=None,
                   method: str = "smacof", max_iter: int = 300) -> Reconstruction:
    """MDS on the average of the per-view distance matrices (paper's baseline).

    Parameters
    ----------
    method : {"smacof", "classical", "authors"}, default "smacof"
        ``classical`` is Torgerson MDS (eigen-decomposition, by Lanczos);
        ``smacof`` refines it with scikit-learn's metric SMACOF, the MDS the
        paper used. ``authors`` is the authors' code literally: the K
        matrices averaged with zeros for the pairs a view does not see
        (:func:`~mpe3d.solvers.starts.authors_average`), then the same MDS, no completion.
    max_iter : int, default 300
        SMACOF iterations.

    Each pair is averaged over the views where both of its points are visible.
    Pairs never seen together are filled by graph distances
    (:func:`~mpe3d.solvers.starts.complete_distances`). There is no ``init``: the baseline is
    itself the smart start. The returned projections are fitted to the embedding
    (:func:`fit_projections`), or the given ones in the fixed setting.
    """
    X = mds_embedding(observations, method, max_iter, random_state)
    P = observations.projections if observations.fixed else fit_projections(X, observations, random_state)
    stress = Stress(observations).value(X, P)
    return Reconstruction(points=X, projections=P, stress=stress,
                          stress_history=np.array([stress]), iterations=0,
                          termination=f"MDS ({method})")
