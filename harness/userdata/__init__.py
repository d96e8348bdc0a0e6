"""A user's own data: view files in, a reconstruction and its report out.

:mod:`.formats` reads and writes views, projections and clouds;
:mod:`.observations` checks the views and makes them observations;
:mod:`.reconstruct` is the validated front door (``mpe3d reconstruct`` and
:func:`mpe3d.reconstruct`), returning a typed result (:mod:`.results`: the
cloud, the cameras and the report); :mod:`.colmap_model`
reads and writes COLMAP sparse models; :mod:`.photos` turns a folder of
photos or a COLMAP database into keypoint views (SIFT, matches and their
tracks, by COLMAP through :mod:`mpe3d.solvers.sfm.colmap`), after
:mod:`.photo_folder` has said which files are photos and which are damaged.

Readers of other tools' files: :mod:`.bundler` (Bundler and BAL),
:mod:`.vgg` (VGG's nview-corners tables); :mod:`.references` reads reference
camera poses (a COLMAP model or a Bundler file) to score photos' poses against.

May import: :mod:`mpe3d.solvers` (the SfM stack included), :mod:`mpe3d.options`,
:mod:`mpe3d.errors`, :mod:`mpe3d.harness.files` and the code identity of
:mod:`mpe3d.harness.tracking.identity` (a report says which code made it).
"""

__all__ = ["bundler", "colmap_model", "formats", "observations", "photo_folder", "photos", "reconstruct", "references",
           "results", "vgg"]
