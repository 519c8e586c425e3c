"""One small se3 fit at import, for the forkserver of :func:`cmax.fitting.fit_windows` only.

The fit's compiled kernels are loaded from numba's on-disk cache at their first call, in each process:
every worker of ``fit_windows`` / ``fit_sequence(jobs=)`` paid it on its first window (``docs/fitting.md``
has the measurement). Listed in :data:`cmax.fitting.batch._PRELOAD`, this module
makes the forkserver run one fit of a synthetic window as it starts, so that the kernels (and torch's and
scipy's first-call work) are loaded once there and every worker forked from it starts with them.

Not imported anywhere else; importing it only costs the one fit (its result is thrown away, its warnings
silenced).
"""
from __future__ import annotations

import warnings

import numpy as np


def warm_events(width: int = 96, height: int = 72, count: int = 6000, seed: int = 0):
    """A synthetic se3 window (``Events``, K (3, 3), speed [m/s]): ``count // 20`` points of a plane 2 m away
    firing 20 events each at uniform times while the camera slides along +x at 0.5 m/s for 0.1 s (20 px of
    flow). Deterministic."""
    from cmax.events import Events

    rng = np.random.default_rng(seed)
    f, speed, depth, duration_us = 80.0, 0.5, 2.0, 100_000
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    points = count // 20
    x0, y0 = np.repeat(rng.uniform(0, width + 20, points), 20), np.repeat(rng.uniform(0, height, points), 20)
    t = rng.integers(0, duration_us, x0.size)
    order = np.argsort(t, kind="stable")
    x0, y0, t = x0[order], y0[order], t[order]
    x = x0 - f * speed * (t * 1e-6) / depth
    keep = (x >= 0) & (x <= width - 1)
    events = Events(np.rint(x[keep]).astype(np.int64), np.rint(y0[keep]).clip(0, height - 1).astype(np.int64),
                    t[keep], np.where(rng.random(int(keep.sum())) < 0.5, 1, -1).astype(np.int64), width, height,
                    time_unit="us")
    return events, K, speed


def warm() -> None:
    """Run the fit (with the defaults ``fit_windows`` workers use: one torch thread)."""
    import torch

    from cmax.fitting.api import fit

    events, K, speed = warm_events()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit(events, K, speed=speed)
    finally:
        torch.set_num_threads(threads)


try:
    warm()
except Exception as error:  # pragma: no cover - the warm-up only saves time: it must never stop the server
    warnings.warn(f"cmax.fitting._warm: the warm-up fit failed ({type(error).__name__}: {error}); the workers "
                  "load the kernels themselves", RuntimeWarning, stacklevel=1)
