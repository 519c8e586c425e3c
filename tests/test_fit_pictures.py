"""The depth pictures of a fitted run share one colour scale (``cmax fit``) and ``FitResult.plot``
draws its depth with a colour bar and the 'no estimate' hatch."""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from cmax import viz
from cmax.cli.fit import _depth_scale


def _window(depth: np.ndarray, mask: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(depth=depth, mask=mask)


def test_one_scale_pools_every_window_and_the_same_depth_gets_the_same_colour():
    near = _window(np.full((8, 10), 1.0), np.ones((8, 10), bool))
    far = _window(np.full((8, 10), 4.0), np.ones((8, 10), bool))
    far.mask[:, :5] = False  # off the mask: not part of the scale
    far.depth[:, :5] = 100.0
    scale = _depth_scale([near, far, _window(None, None)])
    assert scale == viz.DepthScale.from_depths([np.full((8, 10), 1.0), np.full((8, 5), 4.0)])
    assert scale.far < 100.0
    # a wall at 2 m is drawn alike in both windows, whatever else each window holds
    a, b = np.full((8, 10), 2.0), np.full((8, 10), 2.0)
    b[0, 0] = 3.9
    assert np.array_equal(viz.depth_image(a, scale)[4, 4], viz.depth_image(b, scale)[4, 4])


def test_the_scale_is_the_windows_depths_whatever_the_search_range_and_no_depth_gives_none():
    """The scale came from --depth-range when given: a search over 0.05-50 m drew a scene at 0.5-5 m in one
    colour (an audit's Gen4 picture, almost all black). It is the windows' own depths, and None without any."""
    w = _window(np.geomspace(0.5, 5.0, 16).reshape(4, 4), np.ones((4, 4), bool))
    scale = _depth_scale([w])
    assert 0.5 <= scale.near < 0.6 and 4.5 < scale.far <= 5.0
    empty = _window(np.full((4, 4), 2.0), np.zeros((4, 4), bool))
    assert _depth_scale([empty]) is None
    assert _depth_scale([]) is None


def test_fit_result_plot_has_a_colour_bar_and_hatches_pixels_without_depth(tmp_path):
    from cmax.fitting.api import FitResult

    h, w = 30, 40
    depth = np.full((h, w), 2.0)
    mask = np.zeros((h, w), bool)
    mask[:, : w // 2] = True
    fields = {name: None for name in FitResult.__dataclass_fields__}
    fields.update(depth=depth, mask=mask, iwe_before=np.ones((h, w)), iwe_after=np.ones((h, w)),
                  scale_known=True, t_ref_us=50_000)
    result = FitResult(**fields)
    path = result.plot(tmp_path / "fit.png", depth_scale=(1.0, 4.0), zoom=1)
    picture = cv2.imread(str(path))
    expected = viz.depth_panel(np.where(mask, depth, np.nan), viz.DepthScale(1.0, 4.0),
                               "depth [m], t_ref 0.050 s")
    # the depth panel (with its colour bar) is the right end of the picture
    assert picture.shape[1] > 3 * w
    assert np.array_equal(picture[: expected.shape[0], -expected.shape[1]:], expected)
    with pytest.raises(ValueError):
        result.plot(tmp_path / "fit.gif")
    # the same picture in memory (a notebook's), what plot() wrote (PNG: lossless)
    assert np.array_equal(result.image(depth_scale=(1.0, 4.0), zoom=1), picture)


def test_a_fit_results_picture_is_readable_on_a_small_sensor(tmp_path):
    """The picture of a 96x72 fit is enlarged by default (it was 275 px wide, its colour-bar labels overlapping) and
    its titles carry the verdict."""
    from benchmarks.synthetic_windows import make_window
    from cmax.fitting import fit

    w = make_window("slider", 1, width=96, height=72, focal=70.0, duration_s=0.1, max_frames=40)
    r = fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=(0.5, 8.0))
    small, default = r.image(zoom=1), r.image()
    zoom = viz.readable_zoom(96)
    assert zoom > 1 and default.shape[1] > 2 * small.shape[1]
    assert default.shape[1] >= 3 * viz.MIN_PICTURE_WIDTH
    verdict = r.verdict.value.replace("_", " ")
    titled = viz.titled(viz.iwe_image(viz.enlarge(r.iwe_after, zoom)), f"IWE after ({verdict})")
    assert any(np.array_equal(default[: titled.shape[0], x: x + titled.shape[1]], titled)
               for x in range(default.shape[1] - titled.shape[1] + 1))
