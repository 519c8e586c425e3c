"""``import cmax`` gives the sub-packages as attributes on first use, without loading them up front."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import cmax


def test_subpackages_are_reachable_after_a_plain_import():
    code = ("import sys, cmax; assert 'cmax.io' not in sys.modules and 'torch' not in sys.modules;"
            "print(cmax.io.read.__module__, cmax.sim.make_scene.__name__, cmax.representations.voxel_grid.__name__,"
            " cmax.metrics.depth_metrics.__name__, cmax.viz.depth_panel.__name__)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["cmax.io", "make_scene", "voxel_grid", "depth_metrics", "depth_panel"]


def test_unknown_attributes_still_raise():
    with pytest.raises(AttributeError, match="module 'cmax' has no attribute 'nonexistent'"):
        cmax.nonexistent  # noqa: B018
    assert {"io", "sim", "representations", "fit"} <= set(dir(cmax))


def test_events_concatenate_is_cmax_concatenate():
    a = cmax.Events([0, 1], [0, 0], [0, 5], [1, 0], width=2, height=1)
    b = cmax.Events([1], [0], [9], [1], width=2, height=1)
    joined = cmax.Events.concatenate([a, b])
    assert joined == cmax.concatenate([a, b])
    np.testing.assert_array_equal(joined.t, [0, 5, 9])
    with pytest.raises(ValueError, match="back in time"):
        cmax.Events.concatenate([b, a])


def test_every_warning_the_fit_issues_is_reachable_from_cmax():
    """A user who sees ``LowMotionWarning`` printed filters it as ``cmax.LowMotionWarning``."""
    from cmax.fitting import api

    warning_classes = {name for name, value in vars(api).items()
                       if isinstance(value, type) and issubclass(value, Warning) and value.__module__ == api.__name__}
    assert warning_classes == {"LowParallaxWarning", "LowMotionWarning", "BoundWarning"}
    for name in warning_classes:
        assert getattr(cmax, name) is getattr(api, name) and name in cmax.__all__
