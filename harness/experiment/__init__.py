"""Experiments: a run's config, sweeps of them, and one run from config to scores.

:mod:`.config` (every key, validated and hashed), :mod:`.sweep` (a YAML grid
expanded into configs), :mod:`.limits` (what a run or a sweep may ask for),
:mod:`.execute` (one run through the pipeline its config names: the
registry is :func:`.execute.pipeline`), the pipelines themselves
(:mod:`.points_pipeline`, the paper's; :mod:`.colmap_pipeline`, photos
through COLMAP, with :mod:`.colmap_sfm`; :mod:`.tracks_pipeline`, real
keypoints), what a run returns (:mod:`.result`), the solver contract's
checks (:mod:`.contract`) and :mod:`.pictures` (a run's comparison picture).

May import: :mod:`mpe3d.harness.scene`, :mod:`mpe3d.harness.userdata`,
:mod:`mpe3d.harness.tracking` (records and the code identity),
:mod:`mpe3d.harness.files`, :mod:`mpe3d.solvers`, :mod:`mpe3d.plugins`,
:mod:`mpe3d.options` and :mod:`mpe3d.errors`. Never the runner, the command
line or the reports.
"""

__all__ = ["colmap_pipeline", "colmap_sfm", "config", "contract", "execute", "limits", "pictures",
           "points_pipeline", "result", "sweep", "tracks_pipeline"]
