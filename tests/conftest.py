"""Shared fixtures: the real recordings in ``../shared/data`` and small synthetic events."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cmax.events import Events

#: Real test data lives beside the project (``../shared/data``); users who clone
#: the project do not have it, so tests that need it skip with a reason.
SHARED_DATA = Path(
    os.environ.get("EVTSLOWTV_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (set EVTSLOWTV_SHARED_DATA)")
    return SHARED_DATA


def random_events(n: int, width: int = 64, height: int = 48, seed: int = 0, t_span_us: int = 100_000) -> Events:
    """``n`` uniformly random events, sorted by time, for tests."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, t_span_us, n))
    return Events(
        rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n),
        width, height,
    )


@pytest.fixture
def small_events() -> Events:
    """2,000 random events on a 64x48 sensor over 0.1 s."""
    return random_events(2000)
