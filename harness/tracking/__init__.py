"""Tracking and integrity: where finished runs live, and proof of what made them.

:mod:`.store` (the :class:`~.store.Tracker`, a small facade over the rest):
:mod:`.connection` (a store's URI, its server, its errors in one line),
:mod:`.sqlite` (a SQLite store set up safely, or opened read-only),
:mod:`.claims` (who computes which config) and :mod:`.results` (records
logged and read back); :mod:`.records` (what a worker sends back),
:mod:`.journal` (records on disk before MLflow has them, so that no finished
run is lost), :mod:`.ownership` (which process owns a sweep) and
:mod:`.identity` (the fingerprint of the code that computes a run's numbers).

May import: :mod:`mpe3d.harness.files`, :mod:`mpe3d.plugins` (whose code a
plug-in run is) and :mod:`mpe3d.errors`. Nothing above it: a store does not
know what a run is made of.
"""

__all__ = ["claims", "connection", "identity", "journal", "ownership", "records", "results", "sqlite",
           "store"]
