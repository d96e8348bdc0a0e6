"""Structure from motion for keypoints: reprojection error instead of stress.

Camera models (:mod:`.cameras`), observations as flat tracks
(:mod:`.tracks`), two-view checks (:mod:`.epipolar`), triangulation,
Levenberg-Marquardt with the points eliminated (:mod:`.adjust`), the
incremental start (:mod:`.incremental`) and the whole pipeline
(:mod:`.bundle`, what ``objective="reprojection"`` runs).

May import: the stress side of :mod:`mpe3d.solvers` (its public names) and
:mod:`mpe3d.errors`. The stress side never imports this package.
"""
