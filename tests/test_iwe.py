"""Image of warped events: closed-form votes, conservation, blur, gradients, numpy entry."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.iwe import image_of_warped_events, iwe_numpy, polarity_images


def test_bilinear_votes_closed_form():
    x = torch.tensor([1.25, 3.0])
    y = torch.tensor([2.5, 0.0])
    image = image_of_warped_events(x, y, height=4, width=5, sigma=0)
    expected = np.zeros((4, 5), np.float32)
    expected[2, 1], expected[2, 2], expected[3, 1], expected[3, 2] = 0.375, 0.125, 0.375, 0.125
    expected[0, 3] = 1.0
    np.testing.assert_allclose(image.numpy(), expected, atol=1e-6)


def test_integer_coordinates_give_the_event_count_image():
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 20, 500), rng.integers(0, 10, 500)
    counts = np.bincount(y * 20 + x, minlength=200).reshape(10, 20)
    image = iwe_numpy(x.astype(float), y.astype(float), height=10, width=20, sigma=0)
    np.testing.assert_allclose(image, counts)


def test_votes_are_conserved_inside_and_dropped_outside():
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.uniform(2, 28, 1000))
    y = torch.from_numpy(rng.uniform(2, 18, 1000))
    weights = torch.from_numpy(rng.choice([-1.0, 1.0], 1000))
    image = image_of_warped_events(x, y, height=20, width=30, weights=weights, sigma=1.0)
    # The blur loses a little mass at the border only; events are >= 2 px inside.
    assert float(image.sum()) == pytest.approx(float(weights.sum()), abs=0.05 * 1000 ** 0.5)
    outside = image_of_warped_events(torch.tensor([-5.0, 40.0]), torch.tensor([3.0, 3.0]), height=20, width=30, sigma=0)
    assert float(outside.abs().sum()) == 0.0
    half = image_of_warped_events(torch.tensor([-0.5]), torch.tensor([3.0]), height=20, width=30, sigma=0)
    assert float(half.sum()) == pytest.approx(0.5)


def test_batched_equals_one_by_one():
    rng = np.random.default_rng(2)
    x = torch.from_numpy(rng.uniform(0, 15, (3, 200)))
    y = torch.from_numpy(rng.uniform(0, 11, (3, 200)))
    batch = image_of_warped_events(x, y, height=12, width=16)
    for b in range(3):
        torch.testing.assert_close(batch[b], image_of_warped_events(x[b], y[b], height=12, width=16))


def test_gradcheck_coordinates_and_weights():
    torch.manual_seed(0)
    x = (torch.rand(40, dtype=torch.float64) * 10).requires_grad_()
    y = (torch.rand(40, dtype=torch.float64) * 8).requires_grad_()
    w = torch.randn(40, dtype=torch.float64, requires_grad=True)

    def image(x, y, w):
        return image_of_warped_events(x, y, weights=w, height=8, width=10, sigma=0.8)

    assert torch.autograd.gradcheck(image, (x, y, w))


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(x=torch.zeros(3), y=torch.zeros(4)), ValueError, "same shape"),
    (dict(x=torch.zeros(1, 1, 3), y=torch.zeros(1, 1, 3)), ValueError, r"\(N,\) or \(B, N\)"),
    (dict(x=torch.zeros(3, dtype=torch.long), y=torch.zeros(3, dtype=torch.long)), TypeError, "floating-point"),
    (dict(sigma=-1.0), ValueError, "sigma"),
    (dict(height=0), ValueError, "positive"),
    (dict(weights=torch.ones(2)), ValueError, "weights"),
])
def test_bad_input(kwargs, error, match):
    args = dict(x=torch.zeros(3), y=torch.zeros(3), height=4, width=4)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        image_of_warped_events(**args)


def test_sample_bilinear_is_the_adjoint_of_voting_and_differentiable():
    from cmax.iwe import accumulate_bilinear, sample_bilinear

    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 5, 7, dtype=torch.float64, generator=g)
    x = torch.rand(2, 9, dtype=torch.float64, generator=g) * 9 - 1.5  # some points outside
    y = torch.rand(2, 9, dtype=torch.float64, generator=g) * 7 - 1.5
    w = torch.rand(2, 9, dtype=torch.float64, generator=g)
    lhs = (accumulate_bilinear(x, y, w, 5, 7) * images).sum()
    rhs = (w * sample_bilinear(images, x, y)).sum()
    assert float(lhs) == pytest.approx(float(rhs), rel=1e-12)
    assert sample_bilinear(images, torch.tensor([[1.0, -5.0]] * 2, dtype=torch.float64),
                           torch.tensor([[2.0, 2.0]] * 2, dtype=torch.float64))[:, 1].abs().max() == 0
    inside_x = torch.rand(1, 6, dtype=torch.float64, generator=g) * 4 + 1.2
    inside_y = torch.rand(1, 6, dtype=torch.float64, generator=g) * 2 + 1.2
    torch.autograd.gradcheck(lambda im, a, b: sample_bilinear(im, a, b),
                             (images[:1].clone().requires_grad_(), inside_x.requires_grad_(), inside_y.requires_grad_()))
    with pytest.raises(ValueError, match="images"):
        sample_bilinear(images[0], x, y)


def test_polarity_images_are_the_iwes_of_each_polarity_alone():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 50, generator=g, dtype=torch.float64) * 20
    y = torch.rand(2, 50, generator=g, dtype=torch.float64) * 15
    on = (torch.rand(50, generator=g) > 0.4).to(torch.float64)
    images = polarity_images(x, y, on, 16, 21, 1.0)
    assert images.shape == (4, 16, 21)
    for b in range(2):
        keep_on, keep_off = on > 0, on == 0
        expected_on = image_of_warped_events(x[b][keep_on], y[b][keep_on], height=16, width=21, sigma=1.0)
        expected_off = image_of_warped_events(x[b][keep_off], y[b][keep_off], height=16, width=21, sigma=1.0)
        torch.testing.assert_close(images[b], expected_on)
        torch.testing.assert_close(images[2 + b], expected_off)
    weights = torch.full_like(x, 2.0)
    torch.testing.assert_close(polarity_images(x, y, on, 16, 21, 1.0, weights), 2 * images)


def test_a_non_finite_coordinate_makes_the_image_nan_without_indexing_outside():
    """NaN or inf coordinates (a NaN motion) give NaN in the image and in the sampled value, as NaN spreads in
    torch (was: IndexError: index out of range, a device-side assert on CUDA)."""
    from cmax.iwe import accumulate_bilinear, sample_bilinear

    for bad in (float("nan"), float("inf"), -float("inf")):
        x = torch.tensor([1.5, bad, 2.0], dtype=torch.float64)
        y = torch.tensor([1.0, 2.0, bad], dtype=torch.float64)
        image = accumulate_bilinear(x, y, None, 4, 5)
        assert image.shape == (4, 5) and torch.isnan(image).any()
        values = sample_bilinear(torch.ones(1, 4, 5, dtype=torch.float64), x[None], y[None])
        assert float(values[0, 0]) == pytest.approx(1.0) and torch.isnan(values[0, 1:]).all()


def test_blur_refuses_a_negative_or_non_finite_sigma_and_keeps_the_image_at_zero():
    """Was: a negative sigma returned the image unblurred without a word (as sigma 0 does)."""
    from cmax.iwe import blur

    image = torch.rand(5, 6, dtype=torch.float64)
    assert torch.equal(blur(image, 0.0), image)
    for sigma in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="sigma must be a finite number of pixels >= 0"):
            blur(image, sigma)
    blurred = blur(image, 1.0)          # mass conserved away from the border: an interior impulse keeps its sum
    impulse = torch.zeros(21, 21, dtype=torch.float64)
    impulse[10, 10] = 1.0
    assert blur(impulse, 1.0).sum().item() == pytest.approx(1.0, rel=1e-6) and blurred.shape == image.shape
