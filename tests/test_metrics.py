"""Depth and motion metrics on small arrays whose values are worked out by hand in the comments."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cmax.geometry import se3_exp
from cmax.metrics import DepthMetrics, MotionMetrics, depth_metrics, motion_metrics, window_twist

NAN = float("nan")


# -- depth: every metric by hand -------------------------------------------------------------
def test_depth_metrics_hand_computed() -> None:
    # Three valid pixels: (pred, gt) = (2, 1), (2, 2), (3, 4); the fourth has NaN ground truth.
    pred = np.array([[2.0, 2.0], [3.0, 5.0]])
    gt = np.array([[1.0, 2.0], [4.0, NAN]])
    m = depth_metrics(pred, gt)
    # |d-g| = 1, 0, 1; (d-g)^2 = 1, 0, 1; |d-g|/g = 1, 0, 1/4; (d-g)^2/g = 1, 0, 1/4
    assert m.abs_rel == pytest.approx((1 + 0 + 0.25) / 3)
    assert m.sq_rel == pytest.approx((1 + 0 + 0.25) / 3)
    assert m.rmse == pytest.approx(math.sqrt(2 / 3))
    assert m.abs_mean == pytest.approx(2 / 3)
    # log ratios: log 2, 0, log(3/4)
    assert m.rmse_log == pytest.approx(math.sqrt((math.log(2) ** 2 + math.log(0.75) ** 2) / 3))
    # max(d/g, g/d) = 2, 1, 4/3: < 1.25 -> 1 of 3; < 1.5625 -> 2 of 3; < 1.953 -> 2 of 3
    assert (m.delta1, m.delta2, m.delta3) == pytest.approx((1 / 3, 2 / 3, 2 / 3))
    assert m.n_pixels == 3 and m.coverage == 1.0 and m.scale == 1.0 and m.frame_scales == ()
    assert m.n_frames == 1


def test_delta3_threshold_just_above_and_below() -> None:
    # ratios 1.9 (< 1.953125) and 2.0 (not below)
    m = depth_metrics(np.array([[1.9, 2.0]]), np.array([[1.0, 1.0]]))
    assert m.delta3 == pytest.approx(0.5) and m.delta2 == 0.0


def test_cutoff_errors_mvsec_convention() -> None:
    # gt 5, 15, 25, 35 m with errors 1, 2, 3, 4 m
    gt = np.array([[5.0, 15.0, 25.0, 35.0]])
    pred = gt + np.array([[1.0, -2.0, 3.0, -4.0]])
    m = depth_metrics(pred, gt)
    assert m.cutoff_errors == pytest.approx({10.0: 1.0, 20.0: 1.5, 30.0: 2.0})
    assert m.abs_mean == pytest.approx(2.5)
    # a cut-off below every ground truth is NaN, not an error
    m = depth_metrics(pred, gt, cutoffs=(1.0, 40.0))
    assert math.isnan(m.cutoff_errors[1.0]) and m.cutoff_errors[40.0] == pytest.approx(2.5)
    # the cut-off is inclusive: gt == 15 counts at 15 m
    assert depth_metrics(pred, gt, cutoffs=(15.0,)).cutoff_errors[15.0] == pytest.approx(1.5)


def test_coverage_counts_missing_predictions() -> None:
    gt = np.array([[1.0, 2.0], [4.0, NAN]])
    pred = np.array([[1.5, 2.0], [NAN, 3.0]])
    m = depth_metrics(pred, gt)
    # valid gt: 3 pixels; predicted among them: 2 -> 2/3; the prediction on NaN gt is not counted
    assert m.n_pixels == 2 and m.coverage == pytest.approx(2 / 3)
    assert m.abs_mean == pytest.approx(0.25)


def test_non_positive_and_infinite_predictions_are_not_predicted() -> None:
    gt = np.ones((1, 4))
    pred = np.array([[0.0, -1.0, np.inf, 2.0]])
    with pytest.warns(UserWarning, match="1 negative depths"):       # -1: left out, but not without a word
        m = depth_metrics(pred, gt)
    assert m.n_pixels == 1 and m.coverage == pytest.approx(0.25) and m.abs_mean == pytest.approx(1.0)


def test_mask_restricts_pixels_and_coverage() -> None:
    gt = np.array([[1.0, 2.0], [4.0, 8.0]])
    pred = np.array([[2.0, NAN], [4.0, 4.0]])
    mask = np.array([[True, True], [False, True]])
    m = depth_metrics(pred, gt, mask=mask)
    # inside the mask: (2,1) error 1, (NaN,2) missing, (4,8) error 4 -> coverage 2/3, abs mean 2.5
    assert m.n_pixels == 2 and m.coverage == pytest.approx(2 / 3) and m.abs_mean == pytest.approx(2.5)


def test_min_and_max_depth_bound_valid_ground_truth() -> None:
    gt = np.array([[0.0005, 1.0, 50.0]])
    pred = np.array([[1.0, 2.0, 40.0]])
    # 0.0005 <= min_depth (1e-3) is invalid; 50 > max_depth 30 is invalid
    m = depth_metrics(pred, gt, max_depth=30.0)
    assert m.n_pixels == 1 and m.abs_mean == pytest.approx(1.0) and m.coverage == 1.0
    assert depth_metrics(pred, gt).n_pixels == 2


def test_median_scaling_recovers_a_scaled_prediction() -> None:
    gt = np.array([[1.0, 2.0, 4.0]])
    m = depth_metrics(gt / 3.0, gt, median_scaling=True)
    # median(gt) / median(pred) = 2 / (2/3) = 3: after scaling the prediction is exact
    assert m.scale == pytest.approx(3.0) and m.frame_scales == pytest.approx((3.0,))
    assert m.abs_rel == pytest.approx(0.0, abs=1e-12) and m.delta1 == 1.0
    # median of the prediction is 1 while median of gt is 2: scale 2 -> pred (1, 2, 6), errors 0, 0, 2
    m = depth_metrics(np.array([[0.5, 1.0, 3.0]]), gt, median_scaling=True)
    assert m.scale == pytest.approx(2.0) and m.abs_mean == pytest.approx((0 + 0 + 2) / 3)


def test_per_frame_average_differs_from_pooled() -> None:
    # frame 0: one pixel, error 1; frame 1: three pixels, error 0 each
    gt = np.array([[[1.0, NAN], [NAN, NAN]], [[1.0, 1.0], [1.0, NAN]]])
    pred = np.array([[[2.0, 5.0], [5.0, 5.0]], [[1.0, 1.0], [1.0, 5.0]]])
    pooled = depth_metrics(pred, gt)
    per = depth_metrics(pred, gt, per_frame=True)
    assert pooled.abs_mean == pytest.approx(1 / 4)  # (1 + 0 + 0 + 0) / 4
    assert per.abs_mean == pytest.approx(1 / 2)  # (1 + 0) / 2
    assert per.rmse == pytest.approx((1 + 0) / 2) and pooled.rmse == pytest.approx(math.sqrt(1 / 4))
    assert per.n_pixels == pooled.n_pixels == 4 and per.n_frames == 2


def test_per_frame_skips_frames_without_pixels_and_scales_each_frame() -> None:
    gt = np.stack([np.full((2, 2), 2.0), np.full((2, 2), NAN), np.full((2, 2), 4.0)])
    pred = np.stack([np.full((2, 2), 1.0), np.full((2, 2), 1.0), np.full((2, 2), 1.0)])
    m = depth_metrics(pred, gt, per_frame=True, median_scaling=True)
    assert m.n_frames == 2 and m.abs_rel == pytest.approx(0.0, abs=1e-12)
    assert m.frame_scales[0] == pytest.approx(2.0) and math.isnan(m.frame_scales[1])
    assert m.frame_scales[2] == pytest.approx(4.0) and m.scale == pytest.approx(3.0)


def test_per_frame_cutoff_averages_only_frames_within_cutoff() -> None:
    # frame 0: gt 5 m, error 1; frame 1: gt 25 m, error 3 -> err_10m = 1 (only frame 0), err_30m = (1+3)/2
    gt = np.array([[[5.0]], [[25.0]]])
    pred = np.array([[[6.0]], [[28.0]]])
    m = depth_metrics(pred, gt, per_frame=True)
    assert m.cutoff_errors[10.0] == pytest.approx(1.0) and m.cutoff_errors[30.0] == pytest.approx(2.0)


def test_as_dict_flattens_cutoffs() -> None:
    d = depth_metrics(np.array([[2.0]]), np.array([[1.0]])).as_dict()
    assert d["err_10m"] == pytest.approx(1.0) and d["err_30m"] == pytest.approx(1.0)
    assert "cutoff_errors" not in d and d["n_pixels"] == 1


def test_result_is_frozen() -> None:
    m = depth_metrics(np.array([[2.0]]), np.array([[1.0]]))
    assert isinstance(m, DepthMetrics)
    with pytest.raises(AttributeError):
        m.abs_rel = 0.0  # type: ignore[misc]


def test_inputs_are_not_modified_and_float32_works() -> None:
    gt = np.array([[1.0, NAN]], dtype=np.float32)
    pred = np.array([[2.0, 3.0]], dtype=np.float32)
    gt_copy, pred_copy = gt.copy(), pred.copy()
    depth_metrics(pred, gt, median_scaling=True)
    np.testing.assert_array_equal(gt, gt_copy)
    np.testing.assert_array_equal(pred, pred_copy)


# -- depth: bad input ---------------------------------------------------------------------------
def test_depth_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="same shape"):
        depth_metrics(np.ones((2, 3)), np.ones((3, 2)))


@pytest.mark.parametrize("shape", [(4,), (1, 2, 3, 4), (0, 3)])
def test_depth_bad_ndim_raises(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="pred must have shape"):
        depth_metrics(np.ones(shape), np.ones(shape))


def test_no_valid_pixel_raises() -> None:
    with pytest.raises(ValueError, match="no pixel has both"):
        depth_metrics(np.full((2, 2), NAN), np.ones((2, 2)))
    with pytest.raises(ValueError, match="no pixel has both"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2)), mask=np.zeros((2, 2), bool))


def test_bad_mask_and_options_raise() -> None:
    with pytest.raises(TypeError, match="mask must be a boolean"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2)), mask=np.ones((2, 2)))
    with pytest.raises(ValueError, match="mask must have shape"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2)), mask=np.ones((3, 2), bool))
    with pytest.raises(ValueError, match="max_depth must exceed"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2)), max_depth=1e-4)
    with pytest.raises(ValueError, match="cutoffs"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2)), cutoffs=(-1.0,))
    with pytest.raises(TypeError, match="gt must hold real numbers"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 2), bool))


def test_frame_mask_broadcasts_over_frames() -> None:
    gt = np.ones((3, 2, 2))
    pred = np.full((3, 2, 2), 2.0)
    m = depth_metrics(pred, gt, mask=np.array([[True, False], [False, False]]))
    assert m.n_pixels == 3


# -- motion ---------------------------------------------------------------------------------------
def test_motion_metrics_hand_computed() -> None:
    # window 0: v at 90 deg from gt, omega error (1, 0, 0) deg/s
    # window 1: v parallel (same direction, twice as long), omega error (0, 0, -3) deg/s
    v_pred = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    v_gt = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    omega_gt = np.array([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    omega_pred = omega_gt + np.radians([[1.0, 0.0, 0.0], [0.0, 0.0, -3.0]])
    m = motion_metrics(v_pred, omega_pred, v_gt, omega_gt)
    # RMS over 6 components: sqrt((1 + 9) / 6)
    assert m.omega_rms_deg_s == pytest.approx(math.sqrt(10 / 6))
    # v errors: (1, -1, 0) and (0, 0, 1) -> sqrt(3 / 6)
    assert m.v_rms_m_s == pytest.approx(math.sqrt(3 / 6))
    assert m.direction_error_deg == pytest.approx(45.0) and m.direction_error_deg_median == pytest.approx(45.0)
    assert (m.n_windows, m.n_direction) == (2, 2)
    assert isinstance(m, MotionMetrics) and m.as_dict()["v_rms_m_s"] == pytest.approx(math.sqrt(0.5))


def test_direction_error_of_opposite_and_small_angles() -> None:
    m = motion_metrics([-1, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0])
    assert m.direction_error_deg == pytest.approx(180.0)
    tiny = 1e-7  # atan2 keeps the angle accurate where arccos of the dot product would round to 0
    m = motion_metrics([1, tiny, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0])
    assert m.direction_error_deg == pytest.approx(math.degrees(tiny), rel=1e-6)


def test_direction_undefined_for_zero_velocity() -> None:
    v_pred = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    v_gt = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    zeros = np.zeros((3, 3))
    m = motion_metrics(v_pred, zeros, v_gt, zeros)
    assert m.n_direction == 1 and m.direction_error_deg == pytest.approx(45.0)
    m = motion_metrics([0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0])
    assert math.isnan(m.direction_error_deg) and math.isnan(m.direction_error_deg_median)
    assert m.n_direction == 0 and m.v_rms_m_s == pytest.approx(math.sqrt(1 / 3))


def test_direction_median_differs_from_mean() -> None:
    # angles 0, 0, 90 -> mean 30, median 0
    v_pred = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    v_gt = np.array([[1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]])
    m = motion_metrics(v_pred, np.zeros((3, 3)), v_gt, np.zeros((3, 3)))
    assert m.direction_error_deg == pytest.approx(30.0) and m.direction_error_deg_median == pytest.approx(0.0)


def test_motion_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="same shape"):
        motion_metrics(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(3), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"v_pred must have shape \(3,\)"):
        motion_metrics(np.zeros(4), np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="omega_gt must be finite"):
        motion_metrics(np.zeros(3), np.zeros(3), np.zeros(3), [0, NAN, 0])


def test_window_twist_recovers_a_constant_twist() -> None:
    xi = np.array([0.3, -0.1, 0.5, 0.2, -0.4, 0.1])
    T_w_0 = se3_exp(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))
    T_w_1 = T_w_0 @ se3_exp(xi * 0.25)
    np.testing.assert_allclose(window_twist(T_w_0, T_w_1, 0.25), xi, atol=1e-10)
    # pure translation along x by 1 m in 2 s: v = (0.5, 0, 0), omega = 0
    T_w_1 = np.eye(4)
    T_w_1[0, 3] = 1.0
    np.testing.assert_allclose(window_twist(np.eye(4), T_w_1, 2.0), [0.5, 0, 0, 0, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="duration_s must be a positive"):
        window_twist(T_w_0, T_w_1, 0.0)


def test_negative_predicted_depths_are_warned_about_not_scored_silently() -> None:
    """A pixel predicted at -1 m (a sign error) was left out without a word: abs_rel 0, delta1 1.0 on
    [[-1, 1], [1, 1]] against ones, only coverage 0.75 hinting. It still does not enter the errors (no log of a
    negative depth) but is warned about; zeros stay the silent 'no prediction' of dense maps."""
    gt = np.ones((2, 2))
    with pytest.warns(UserWarning, match=r"pred holds 1 negative depths \(down to -1 m\).*coverage 0.750"):
        m = depth_metrics(np.array([[-1.0, 1.0], [1.0, 1.0]]), gt)
    assert m.coverage == 0.75 and m.abs_rel == 0.0
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert depth_metrics(np.array([[0.0, 1.0], [NAN, 1.0]]), gt).coverage == 0.5
    with pytest.raises(ValueError, match="0 positive finite predictions, 4 negative ones"):
        depth_metrics(-gt, gt)


def test_an_integer_depth_map_of_millimetres_is_warned_about() -> None:
    """A uint16 ground truth of millimetres (or KITTI's depth x 256) was read as metres without a word
    (abs_rel 0.999 against the right prediction)."""
    metres = np.array([[1.0, 2.0], [4.0, 8.0]])
    with pytest.warns(UserWarning, match=r"gt holds integers \(uint16\) up to 8,000, read as metres"):
        depth_metrics(metres, (metres * 1000).astype(np.uint16))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert depth_metrics(metres, metres.astype(np.uint16)).abs_rel == 0.0    # whole metres: no warning
