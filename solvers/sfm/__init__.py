"""Structure from motion for keypoints: reprojection error instead of stress.

Camera models (:mod:`.cameras`), observations as flat tracks
(:mod:`.tracks`), two-view checks (:mod:`.epipolar`), triangulation,
Levenberg-Marquardt with the points eliminated (:mod:`.adjust`), the
incremental start (:mod:`.incremental`, affine; :mod:`.pinhole_start`, perspective, grown view
by view with pycolmap's robust two-view and absolute-pose estimators), what a
fit rests on (:mod:`.support`), the camera models' starts and fits
(:mod:`.camera_fits`), the rounds of wrong matches (:mod:`.outliers`) and the
whole pipeline (:mod:`.bundle`, what ``objective="reprojection"`` runs;
:mod:`.camera_groups` for photos of several cameras, a focal length each).
COLMAP's own mapper on the same tracks is a method beside it
(:mod:`.colmap_mapper`); :mod:`.colmap` is the one module that calls
pycolmap, for both and for the harness (photos, databases, models);
:mod:`.methods` is the plug-in kind for SfM methods of a user's own. Its
compiled kernels sit beside them: :mod:`.kernels` (bundle adjustment's) and
:mod:`.epipolar_kernels` (the two-view tests').

May import: the stress side of :mod:`mpe3d.solvers`, :mod:`mpe3d.options`,
:mod:`mpe3d.plugins` (whose SfM method a name is) and :mod:`mpe3d.errors`. The stress side never imports this package.
"""

__all__ = ["adjust", "bundle", "camera_fits", "camera_groups", "cameras", "colmap", "colmap_mapper", "epipolar",
           "epipolar_kernels", "incremental", "kernels", "methods", "outliers", "pinhole_start", "support",
           "tracks", "triangulation"]
