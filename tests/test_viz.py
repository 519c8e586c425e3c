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


# -- depth pictures: one scale for many windows, "no estimate" apart from every depth -------------
def _magma() -> np.ndarray:
    import cv2

    return cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_MAGMA)[:, 0].astype(int)


def test_one_depth_scale_gives_one_depth_one_colour_in_two_windows():
    first = np.full((8, 8), 2.0, np.float32)
    second = np.full((8, 8), 2.0, np.float32)
    first[:4], second[:4] = 1.2, 5.0                   # the windows see different depth ranges
    scale = viz.DepthScale.from_depths([first, second])
    assert (scale.near, scale.far) == pytest.approx((float(np.percentile([1.2] * 32 + [2.0] * 96 + [5.0] * 32, 1)),
                                                     float(np.percentile([1.2] * 32 + [2.0] * 96 + [5.0] * 32, 99))))
    a, b = viz.depth_image(first, scale), viz.depth_image(second, scale)
    np.testing.assert_array_equal(a[6, 6], b[6, 6])    # 2 m: one colour in both windows
    # each window on its own percentiles would draw 2 m differently: far end in one, near end in the other
    assert not np.array_equal(viz.depth_image(first)[6, 6], viz.depth_image(second)[6, 6])
    # the colour is magma at the inverse-depth level of 2 m
    level = (1 / 2.0 - 1 / scale.far) / (1 / scale.near - 1 / scale.far)
    np.testing.assert_array_equal(a[6, 6], _magma()[int(255 * level)])


def test_no_estimate_is_drawn_in_colours_outside_the_colour_map():
    depth = np.full((16, 16), 3.0, np.float32)
    depth[:, :8] = np.nan
    depth[0, 8] = -1.0                                   # <= 0 is no estimate too
    picture = viz.depth_image(depth, (1.0, 6.0)).astype(int)
    hidden = picture[np.isnan(depth) | (depth <= 0)]
    distance = np.abs(hidden[:, None, :] - _magma()[None]).max(axis=2).min(axis=1)
    assert distance.min() >= 60                          # no "no estimate" pixel looks like any depth
    assert {tuple(c) for c in hidden} == {viz.NO_DEPTH_BGR, viz.NO_DEPTH_HATCH_BGR}   # the hatch: two greys


def test_depth_panel_has_a_colour_bar_labelled_in_metres():
    scale = viz.DepthScale(1.0, 4.0)
    depth = np.full((60, 80), 2.0, np.float32)
    panel = viz.depth_panel(depth, scale, "depth")
    assert panel.shape[1] > 80 + 4 + 30                  # map + gap + bar with its labels
    bar = panel[-60:, 84:]
    # the bar runs the whole colour map: near (magma's brightest) at its top, far (darkest) at its bottom
    column = bar[:, 2].astype(int)
    magma = _magma()
    rows = [r for r in range(60) if np.abs(magma - column[r]).max(axis=1).min() <= 2]
    assert len(rows) >= 20
    assert column[rows[0]].sum() > column[rows[-1]].sum() + 300
    # the "no estimate" swatch sits below the bar
    assert (np.abs(bar[-6:, 2].astype(int) - np.array(viz.NO_DEPTH_BGR)).max(axis=1) <= 48).all()
    # tick labels are text: dark pixels right of the bar
    assert (bar[:, 20:] < 100).any()
    np.testing.assert_allclose(scale.ticks(5)[[0, -1]], [1.0, 4.0])


def test_event_panel_shows_the_on_off_legend_in_the_colours_of_the_events():
    counts = np.zeros((2, 40, 200), np.float32)
    counts[1, 10, 10] = counts[0, 20, 20] = 1            # one ON, one OFF event
    panel = viz.event_panel(counts, "events")
    picture = panel[-40:]
    np.testing.assert_array_equal(picture[10, 10], viz.ON_BGR)
    np.testing.assert_array_equal(picture[20, 20], viz.OFF_BGR)
    strip = panel[:-40].reshape(-1, 3)
    assert (strip == viz.ON_BGR).all(axis=1).sum() >= 25 and (strip == viz.OFF_BGR).all(axis=1).sum() >= 25
    # a narrow picture gets the legend on a second line rather than over the title
    narrow = viz.event_panel(counts[:, :, :60], "a long title of events")
    assert narrow.shape[0] - 40 > panel.shape[0] - 40


def test_titles_grow_with_wide_pictures():
    small = viz.titled(np.zeros((10, 320, 3), np.uint8), "t")
    wide = viz.titled(np.zeros((10, 1280, 3), np.uint8), "t")
    assert wide.shape[0] - 10 >= 2 * (small.shape[0] - 10)


@pytest.mark.parametrize("name, magic", [("a.png", b"\x89PNG"), ("a.jpg", b"\xff\xd8\xff"), ("a.JPEG", b"\xff\xd8\xff")])
def test_save_image_follows_the_extension(tmp_path, name, magic):
    path = viz.save_image(tmp_path / name, np.zeros((4, 4, 3), np.uint8))
    assert path.read_bytes()[:len(magic)] == magic


@pytest.mark.parametrize("name", ["a.tif", "a", "a.png.bak"])
def test_save_image_refuses_other_extensions(tmp_path, name):
    with pytest.raises(ValueError, match="must end in .png, .jpg, .jpeg"):
        viz.save_image(tmp_path / name, np.zeros((4, 4, 3), np.uint8))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("call, error, match", [
    (lambda: viz.DepthScale(2.0, 1.0), ValueError, "0 < near < far"),
    (lambda: viz.DepthScale(0.0, 1.0), ValueError, "0 < near < far"),
    (lambda: viz.DepthScale(1.0, float("inf")), ValueError, "finite"),
    (lambda: viz.DepthScale("1", 2.0), TypeError, "numbers of metres"),
    (lambda: viz.DepthScale.from_depths([np.full((2, 2), np.nan)]), ValueError, "no positive finite depth"),
    (lambda: viz.depth_image(np.ones((4, 4)), (1, 2), depth_range=(1, 2)), TypeError, "not both"),
    (lambda: viz.event_frame_image(np.zeros((2, 4, 4)), gamma=0), ValueError, r"gamma must be a number in \(0, 1\]"),
    (lambda: viz.grid([np.zeros((2, 2, 3), np.uint8)], 0), ValueError, "columns must be an integer >= 1"),
])
def test_picture_settings_are_validated(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_gamma_and_percentile_lift_faint_events_beside_a_bright_blob():
    counts = np.zeros((2, 20, 20), np.float32)
    counts[1, :4, :4] = 50                               # a flickering lamp: 16 very active pixels
    counts[1, 10:, :] = 1                                # the scene: 200 pixels with one event
    plain = viz.event_frame_image(counts)                # 99th percentile: the lamp sets the scale
    robust = viz.event_frame_image(counts, percentile=90, gamma=0.5)
    assert plain[15, 5, 2] > 240                         # one event is almost white (1/50 of the ink)
    assert robust[15, 5, 2] == 0 and robust[0, 0, 2] == 0   # the scene's events and the lamp: full ink


def test_long_titles_wrap_instead_of_running_off_the_picture():
    short = viz.titled(np.zeros((10, 120, 3), np.uint8), "events")
    long = viz.titled(np.zeros((10, 120, 3), np.uint8), "recording.h5, 0.1 s + 50 ms: 12,345 events")
    assert long.shape[0] - 10 >= 2 * (short.shape[0] - 10)
    strip = long[:-10]
    assert (strip[:, -6:] == 255).all()                  # nothing drawn into the right margin


def test_depth_colour_bar_states_its_unit_or_none_for_depth_up_to_scale():
    scale = viz.DepthScale(1.0, 4.0)
    metres = viz.depth_colour_bar(80, scale)
    bare = viz.depth_colour_bar(80, scale, unit="")
    assert bare.shape[1] < metres.shape[1]   # the labels lose their " m"
    with pytest.raises(TypeError, match="unit must be a string"):
        viz.depth_colour_bar(80, scale, unit=None)
    assert viz.depth_panel(np.full((60, 80), 2.0, np.float32), scale, "depth (up to scale)", unit="").shape[1] > 80 + 30


def test_depth_colour_bar_ends_say_they_saturate():
    """Was: the ends read "1.83 m" and "5.86 m" although every nearer (farther) depth takes the end's colour
    (the demo's cmax.fit map holds many pixels nearer than its shared scale): the ends now read <= and >=."""
    scale = viz.DepthScale(1.0, 4.0)
    assert viz.depth_bar_labels(scale.ticks(3)) == ["<= 1 m", "1.6 m", ">= 4 m"]
    assert viz.depth_bar_labels(scale.ticks(3), "") == ["<= 1", "1.6", ">= 4"]
    # the clipping it names: a depth at half the near end is drawn in the near end's colour
    near = viz.depth_image(np.array([[0.5, 1.0]], np.float32), scale)
    assert (near[0, 0] == near[0, 1]).all()


def test_wrapped_titles_of_wide_pictures_stay_inside_the_picture():
    # at widths where the text is drawn with a 2 px stroke, wrapping measures with that stroke too
    for width in (1400, 1817, 2600):
        title = " ".join(f"word{k}: abs_rel 0.123, Abs mean 4.56 m" for k in range(12))
        picture = viz.titled(np.full((40, width, 3), 255, np.uint8), title)
        strip = picture[:-40]
        assert (strip[:, -3:] == 255).all(), width   # no text reaches the right edge
        assert (strip < 128).any()                    # and the text is there


def test_the_event_volume_bins_carry_the_colour_bar_of_their_scale():
    """One bin holds +2 and -2 events at two pixels (the rest 0): the bar beside the bins runs from the blue of +2
    (top) through white to the red of -2 (bottom), the colours the pixels have; without a unit, no bar."""
    volume = np.zeros((2, 60, 80), np.float32)
    volume[0, 10, 10], volume[1, 30, 40] = 2.0, -2.0
    bare = viz.voxel_grid_image(volume, unit=None, percentile=100.0)
    picture = viz.voxel_grid_image(volume, percentile=100.0)
    assert picture.shape[1] > bare.shape[1] + 40 and picture.shape[0] == bare.shape[0]
    bar = picture[:, bare.shape[1] + 4: bare.shape[1] + 4 + 12]
    column = bar[:, 6].astype(int)
    painted = np.flatnonzero((column != 255).any(axis=1))
    top, bottom = column[painted[0]], column[painted[-1]]
    positive = viz.signed_image(np.array([[2.0]]), scale=2.0)[0, 0]
    negative = viz.signed_image(np.array([[-2.0]]), scale=2.0)[0, 0]
    np.testing.assert_array_equal(top, positive)
    np.testing.assert_array_equal(bottom, negative)
    middle = column[(painted[0] + painted[-1]) // 2]
    assert (middle > 240).all()                                  # white at zero
