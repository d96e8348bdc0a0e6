"""Synthetic scenes: a mesh, its ground truth and what a solver may see of it.

Shapes (bundled meshes and procedural ones), viewpoints (the views'
rotations and angle bands), visibility, noise, :mod:`.observe` (ground truth
to :class:`mpe3d.solvers.Observations`), the metrics that score a
reconstruction against the ground truth (CD, EMD, ROA) and ray-traced renderings
for the colmap experiment.

May import: :mod:`mpe3d.solvers` (its public types), :mod:`mpe3d.plugins`
(datasets from plug-ins) and :mod:`mpe3d.errors`. Nothing else of the
harness: a scene is built from a run's keys, whoever holds them.
"""

__all__ = ["metrics", "noise", "observe", "rendering", "shapes", "viewpoints", "visibility"]
