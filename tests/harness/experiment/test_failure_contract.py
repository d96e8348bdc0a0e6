"""The one error a finished run may end in: a method that registered fewer than two views."""
from types import SimpleNamespace

import numpy as np
import pytest

from mpe3d.errors import MpeError, Unregistered
from mpe3d.harness.experiment import colmap_pipeline


class _Tracks:
    conflicting = 0

    def views_per_track(self):
        return np.array([2, 3, 3, 2])

    def views(self):
        return [{"name": "a"}, {"name": "b"}]


@pytest.fixture
def track_scores(monkeypatch):
    """``_track_scores`` on four tracks COLMAP triangulated, each method raising ``error``."""
    monkeypatch.setattr(colmap_pipeline.colmap_sfm, "triangulated", lambda tracks, sfm: {i: i for i in range(4)})
    monkeypatch.setattr(colmap_pipeline.photos, "tied_views", lambda views: views)
    sfm = SimpleNamespace(point_ids=np.arange(4), points=np.eye(4, 3))

    def scores(error):
        def fed_to(method, *args):
            raise error
        monkeypatch.setattr(colmap_pipeline, "_fed_to", fed_to)
        return colmap_pipeline._track_scores(_Tracks(), sfm, (1.0, np.eye(3), np.zeros(3)), np.eye(3),
                                             (160.0, 120.0), np.random.default_rng(0))
    return scores


def test_a_method_fed_colmaps_tracks_that_registers_nothing_is_a_note(track_scores):
    out, notes = track_scores(Unregistered("registered no two views"))
    assert out["tracks_triangulated"] == 4 and "tracks_bundle_s" not in out
    assert notes == [f"tracks -> {m}: registered no two views" for m in colmap_pipeline.TRACK_METHODS]


def test_any_other_error_of_a_method_fed_colmaps_tracks_fails_the_run(track_scores):
    """Before: every MpeError became a note, and the run FINISHED without that method's scores."""
    with pytest.raises(MpeError, match="share too few points"):
        track_scores(MpeError("views [0] and [1] share too few points to be tied together"))
