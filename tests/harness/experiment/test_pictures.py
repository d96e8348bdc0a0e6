"""The per-run comparison picture: one figure per process, redrawn per run."""

import io

import numpy as np
from PIL import Image

from mpe3d.harness.experiment import pictures


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_a_picture_shows_only_its_own_run(rng):
    """The reused figure carries nothing over: the second of two pictures is
    the picture a fresh process would draw, and differs from the first."""
    a = rng.normal(size=(300, 3))
    b = rng.uniform(size=(500, 3)) * [3.0, 1.0, 0.2]
    pictures.comparison_png(a, a + 0.05, "first run, a long title")
    second = pictures.comparison_png(b, b[::-1], "second")
    pictures.FIGURE_CACHE.clear()  # as in a new process
    fresh = pictures.comparison_png(b, b[::-1], "second")
    assert np.array_equal(_pixels(second), _pixels(fresh))
    assert not np.array_equal(_pixels(second), _pixels(pictures.comparison_png(a, a, "second")))


def test_each_dpi_keeps_its_own_frame(tmp_path, rng):
    points = rng.normal(size=(200, 3))
    small = _pixels(pictures.comparison_png(points, points, "t"))
    pictures.draw_comparison(points, points, tmp_path / "big.png", "t", dpi=110)
    big = np.asarray(Image.open(tmp_path / "big.png").convert("RGB"))
    assert big.shape[0] > small.shape[0] * 1.4  # 110 against 72 dpi
    assert big.std() > 5 and small.std() > 5  # not blank


def test_both_clouds_are_drawn_in_their_colours(rng):
    """The truth's pale discs and the reconstruction's dark dots both reach the
    pixels (markers stamped by Agg, with edges of no width)."""
    truth = rng.normal(size=(400, 3))
    pixels = _pixels(pictures.comparison_png(truth, truth + 2.0, "apart"))

    def near(colour: str) -> int:
        rgb = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(pixels - rgb).sum(axis=2) < 40).sum())
    assert near(pictures.OURS_STYLE["c"]) > 400  # a few pixels per dot
    assert near("#bbdaea") > 400  # the pale discs over white (alpha 0.7)
