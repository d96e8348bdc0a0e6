"""Tracking and integrity: where finished runs live, and proof of what made them.

:mod:`.store` (MLflow: runs, tags, artifacts, the :class:`~.store.Tracker`),
:mod:`.records` (what a worker sends back), :mod:`.journal` (records on disk
before MLflow has them, so that no finished run is lost),
:mod:`.ownership` (which process owns a sweep) and :mod:`.identity` (the
fingerprint of the code that computes a run's numbers).

May import: :mod:`mpe3d.harness.files` and :mod:`mpe3d.errors`. Nothing above
it: a store does not know what a run is made of.
"""
