"""cmax.viz: the picture of an image of warped events."""
from __future__ import annotations

import numpy as np
import pytest

from cmax import viz


def test_iwe_image_is_white_where_empty_and_black_from_the_saturation_on():
    image = np.zeros((4, 5), np.float32)
    image[1, 1], image[2, 2], image[3, 3] = 1.0, 2.0, 4.0
    picture = viz.iwe_image(image, scale=2.0)
    assert picture.shape == (4, 5, 3) and picture.dtype == np.uint8
    assert (picture[0, 0] == 255).all()                       # no events: white
    assert (picture[1, 1] == 127).all()                       # half the scale: mid grey (255 - 127.5, truncated)
    assert (picture[2, 2] == 0).all() and (picture[3, 3] == 0).all()   # at and beyond the scale: black


def test_iwe_image_default_scale_is_the_99th_percentile_of_the_events():
    image = np.zeros((10, 10), np.float32)
    image.flat[:50] = np.arange(1, 51)
    expected = float(np.percentile(np.arange(1, 51), 99))
    assert viz.robust_max(image) == pytest.approx(expected)
    np.testing.assert_array_equal(viz.iwe_image(image), viz.iwe_image(image, scale=expected))


@pytest.mark.parametrize("image, scale, match", [
    (np.zeros((2, 3, 4)), None, r"image must have shape \(H, W\)"),
    (np.full((3, 3), np.nan), None, r"image must be finite"),
    (np.ones((3, 3)), 0.0, r"scale must be a positive number"),
])
def test_iwe_image_rejects_bad_input(image, scale, match):
    with pytest.raises(ValueError, match=match):
        viz.iwe_image(image, scale=scale)
