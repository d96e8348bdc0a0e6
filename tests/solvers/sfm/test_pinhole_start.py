"""The pinhole start grown view by view, and the choice between the two pinholes."""
import numpy as np
import pytest

from mpe3d.harness.scene.rendering import spiral_cameras
from mpe3d.solvers.sfm.pinhole_start import MAX_ERROR, pinhole_start
from mpe3d.solvers.sfm.tracks import Tracks, residual_lengths
from tests.helpers import similarity_rms

pytest.importorskip("pycolmap")


def _close_photos(rng, n=400, views=10, wrong=0.05):
    """A cloud photographed from 1.5 diagonals on half a turn (18 degrees apart),
    each point in a random 70 % of the views, 0.3 px noise and a share of wrong
    matches (an observation moved to another point's place in its view)."""
    X = rng.uniform(-0.3, 0.3, (n, 3))
    cams = spiral_cameras(views, size=400, turns=0.5)
    view, point, z, moved = [], [], [], []
    for k, (R, t) in enumerate(zip(cams.rotations, cams.translations)):
        seen = np.flatnonzero(rng.random(n) < 0.7)
        x = X[seen] @ R.T + t
        xy = cams.focal * x[:, :2] / x[:, 2:] + 200 + 0.3 * rng.standard_normal((len(seen), 2))
        bad = rng.random(len(seen)) < wrong
        rows = np.flatnonzero(bad)
        source = rng.permutation(rows)
        xy[rows] = xy[source]
        changed = np.zeros(len(seen), dtype=bool)
        changed[rows[source != rows]] = True  # a row given its own place is no wrong match
        moved.append(changed)
        view.append(np.full(len(seen), k))
        point.append(seen)
        z.append(xy)
    tracks = Tracks(np.concatenate(view), np.concatenate(point), np.concatenate(z), n, views)
    return tracks, X, cams, np.concatenate(moved)


def test_close_photos_far_apart_are_registered_with_their_focal_length(rng):
    tracks, X, cams, moved = _close_photos(rng)
    start = pinhole_start(tracks, (200.0, 200.0))
    assert start.registered.all() and start.placed.sum() >= 0.9 * len(X)
    assert abs(start.cameras.focal()[0] / cams.focal - 1) < 0.03
    kept = residual_lengths(start.X, start.cameras, tracks, start.kept)
    assert kept.max() <= MAX_ERROR and np.median(kept) < 0.5
    centres = -np.einsum("kji,kj->ki", start.cameras.current_rotations(), start.cameras.params[:, 3:6])
    assert similarity_rms(centres, cams.centres) < 0.01 * np.ptp(cams.centres, axis=0).max()
    assert moved.sum() > 50 and start.kept[moved].mean() < 0.1  # wrong matches are left out


def test_no_pair_to_start_from_is_none(rng):
    tracks, _, _, _ = _close_photos(rng, n=20)  # too few shared points for an essential matrix
    assert pinhole_start(tracks, (200.0, 200.0)) is None
