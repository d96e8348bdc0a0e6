"""The per-run comparison picture: one figure per process, redrawn per run."""

import io

import numpy as np
from PIL import Image

from mpe3d.harness.experiment import pictures as render


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_a_picture_shows_only_its_own_run(rng):
    """The reused figure carries nothing over: the second of two pictures is
    the picture a fresh process would draw, and differs from the first."""
    a = rng.normal(size=(300, 3))
    b = rng.uniform(size=(500, 3)) * [3.0, 1.0, 0.2]
    render.comparison_png(a, a + 0.05, "first run, a long title")
    second = render.comparison_png(b, b[::-1], "second")
    render.FIGURE_CACHE.clear()  # as in a new process
    fresh = render.comparison_png(b, b[::-1], "second")
    assert np.array_equal(_pixels(second), _pixels(fresh))
    assert not np.array_equal(_pixels(second), _pixels(render.comparison_png(a, a, "second")))


def test_each_dpi_keeps_its_own_frame(tmp_path, rng):
    points = rng.normal(size=(200, 3))
    small = _pixels(render.comparison_png(points, points, "t"))
    render.render_comparison(points, points, tmp_path / "big.png", "t", dpi=110)
    big = np.asarray(Image.open(tmp_path / "big.png").convert("RGB"))
    assert big.shape[0] > small.shape[0] * 1.4  # 110 against 72 dpi
    assert big.std() > 5 and small.std() > 5  # not blank
