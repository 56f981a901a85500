"""Filmstrips and thumbnails for the panels."""

import numpy as np
import pytest

from studio.ui.images import filmstrip, side_by_side, thumbnail


def test_filmstrip_grid_and_order():
    frames = np.stack([np.full((24, 32, 3), 20 * i, np.uint8) for i in range(10)])
    strip = filmstrip(frames, cols=5, height=24, gap=2)
    assert strip.shape == (2 * 24 + 2, 5 * 32 + 4 * 2, 3)
    assert strip[5, 5, 0] == 0 and strip[30, 4 * 34 + 5, 0] == 180  # first and last frame in place
    labelled = filmstrip(frames, cols=5, height=24, labels=[str(i) for i in range(10)])
    assert not np.array_equal(labelled, strip)
    with pytest.raises(ValueError, match="filmstrip needs"):
        filmstrip(np.zeros((24, 32, 3), np.uint8))


def test_thumbnail_keeps_aspect_and_side_by_side_aligns():
    img = np.zeros((240, 320, 3), np.uint8)
    assert thumbnail(img, 60).shape == (60, 80, 3)
    assert side_by_side(img, np.zeros((224, 224, 3), np.uint8), height=50, gap=4).shape == (
        50,
        67 + 4 + 50,
        3,
    )
