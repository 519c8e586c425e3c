"""Contrast objectives and regularizers: closed forms, shapes, errors, float64 gradchecks."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.iwe import accumulate_bilinear_indexed, blur
from cmax.objectives import (
    contrast_of_images, deformation, gradient_magnitude, local_contrast, multi_reference_contrast,
    total_variation, variance,
)


@pytest.mark.parametrize("kind", ["variance", "gradient"])
def test_polarity_split_contrast_is_the_sum_over_the_two_images(kind):
    """``on=``: the contrast of the ON events' IWE plus that of the OFF events' (each built here on its
    own), for every reference; with only ON events it is the contrast without the split."""
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.uniform(2, 37, (3, 500)))
    y = torch.from_numpy(rng.uniform(2, 27, (3, 500)))
    on = torch.from_numpy(rng.integers(0, 2, 500))
    split = multi_reference_contrast(x, y, height=30, width=40, kind=kind, on=on)
    parts = [multi_reference_contrast(x[:, on == value], y[:, on == value], height=30, width=40, kind=kind)
             for value in (1, 0)]
    assert float(split) == pytest.approx(float(parts[0] + parts[1]), rel=1e-12)
    all_on = multi_reference_contrast(x, y, height=30, width=40, kind=kind, on=torch.ones(500))
    assert float(all_on) == pytest.approx(float(multi_reference_contrast(x, y, height=30, width=40, kind=kind)))


def test_variance_and_gradient_closed_form_and_batch():
    image = torch.tensor([[0.0, 2.0], [0.0, 2.0]])
    assert float(variance(image)) == pytest.approx(1.0)
    assert variance(torch.stack([image, 2 * image])).tolist() == pytest.approx([1.0, 4.0])
    ramp = torch.arange(5.0).repeat(5, 1)  # dI/dx = 1 in the interior
    assert float(gradient_magnitude(ramp)) == pytest.approx(1.0)
    assert contrast_of_images(torch.stack([image]), "gradient").shape == (1,)
    with pytest.raises(ValueError, match="contrast"):
        contrast_of_images(image[None], "entropy")
    with pytest.raises(ValueError, match="images"):
        variance(torch.zeros(2, 2, 2, 2))


def test_sharper_iwe_has_higher_multi_reference_contrast():
    rng = np.random.default_rng(0)
    x = torch.from_numpy(np.repeat(rng.uniform(5, 35, 40), 20))
    y = torch.from_numpy(np.repeat(rng.uniform(5, 25, 40), 20))
    noise = torch.from_numpy(rng.normal(0, 2, (2, x.numel())))
    sharp = multi_reference_contrast(x[None], y[None], height=30, width=40)
    smeared = multi_reference_contrast((x + noise[0])[None], (y + noise[1])[None], height=30, width=40)
    assert float(sharp) > 1.5 * float(smeared)
    normalised = multi_reference_contrast(x[None], y[None], height=30, width=40, baseline=sharp.detach())
    assert float(normalised) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="same shape"):
        multi_reference_contrast(x, y, height=30, width=40)


def test_gradcheck_contrasts():
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.uniform(2, 14, (2, 30))).requires_grad_()
    y = torch.from_numpy(rng.uniform(2, 10, (2, 30))).requires_grad_()
    for kind in ("variance", "gradient"):
        assert torch.autograd.gradcheck(
            lambda a, b: multi_reference_contrast(a, b, height=12, width=16, sigma=0.8, kind=kind), (x, y))


def test_blur_is_the_2d_gaussian_convolution_with_zero_padding():
    """The OpenCV path on the CPU equals torch's conv2d with the outer-product kernel of
    exp(-d^2 / 2 sigma^2) (radius ceil(3 sigma), normalised), zero padding, in float32 and float64."""
    import math

    for dtype, tolerance in ((torch.float32, 1e-6), (torch.float64, 1e-12)):
        images = torch.rand(3, 23, 31, dtype=dtype, generator=torch.Generator().manual_seed(1))
        sigma = 1.3
        radius = math.ceil(3 * sigma)
        taps = torch.exp(-torch.arange(-radius, radius + 1, dtype=dtype) ** 2 / (2 * sigma ** 2))
        kernel = torch.outer(taps, taps) / taps.sum() ** 2
        expected = torch.nn.functional.conv2d(images[:, None], kernel[None, None], padding=radius)[:, 0]
        torch.testing.assert_close(blur(images, sigma), expected, atol=tolerance, rtol=0)
        assert blur(images, sigma).dtype == dtype


def test_blur_backward_is_exact():
    image = torch.rand(2, 9, 11, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda im: blur(im, 1.3), (image,))


def test_deformation_zero_for_rigid_motion_positive_for_zoom():
    ys, xs = torch.meshgrid(torch.arange(5.0, dtype=torch.float64), torch.arange(6.0, dtype=torch.float64), indexing="ij")
    assert float(deformation(xs, ys, xs + 3.0, ys - 2.0)) == pytest.approx(0.0, abs=1e-12)
    zoom = float(deformation(xs, ys, 0.5 * xs, 0.5 * ys))
    assert zoom == pytest.approx(np.log(0.25) ** 2)
    x1 = (xs * 0.9).requires_grad_()
    assert torch.autograd.gradcheck(lambda a: deformation(xs, ys, a, ys * 1.1), (x1,))


def test_total_variation_closed_form_and_gradcheck():
    grid = torch.tensor([[0.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    # dx = 1 on the left column, 0 elsewhere; dy = 0: mean of sqrt(1 + e^2), sqrt(e^2)...
    expected = (2 * np.sqrt(1 + 1e-6) + 2 * 1e-3) / 4
    assert float(total_variation(grid)) == pytest.approx(expected)
    g = torch.rand(3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(total_variation, (g,))
    with pytest.raises(ValueError, match="gh, gw"):
        total_variation(torch.zeros(3))


def test_local_contrast_ignores_other_cells_events():
    # Two cells; cell 0's events sit on a point, cell 1's are spread. Moving cell 1's
    # events onto cell 0's point raises the global variance but not cell 0's energy.
    origins = torch.tensor([[0.0, 0.0], [10.0, 0.0]], dtype=torch.float64)
    x = torch.tensor([3.0] * 10 + list(np.arange(10.0, 20.0)), dtype=torch.float64)
    y = torch.full((20,), 4.0, dtype=torch.float64)
    cell = torch.tensor([0] * 10 + [1] * 10)
    e = local_contrast(x, y, cell, origins, count=2, patch=(10, 10), sigma=0)
    assert float(e[0]) == pytest.approx(100.0) and float(e[1]) == pytest.approx(10.0)
    moved = local_contrast(torch.where(cell == 1, 3.0, x), y, cell, origins, count=2, patch=(10, 10), sigma=0)
    assert float(moved[0]) == pytest.approx(100.0)  # cell 1's events left its patch: lost, not added to cell 0
    batch = local_contrast(torch.stack([x, x]), torch.stack([y, y]), cell, origins, count=2, patch=(10, 10))
    assert batch.shape == (2, 2)
    xg = (x[5:15] + 0.3).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a: local_contrast(a, y[5:15] + 0.2, cell[5:15], origins, count=2, patch=(10, 10), sigma=0.7), (xg,))


def test_indexed_accumulation_matches_closed_form():
    image = accumulate_bilinear_indexed(torch.tensor([1.5, 0.0]), torch.tensor([0.0, 1.0]), None,
                                        torch.tensor([1, 0]), 2, 3, 3)
    assert image.shape == (2, 3, 3)
    assert image[1, 0, 1] == 0.5 and image[1, 0, 2] == 0.5 and image[0, 1, 0] == 1.0
