"""The network trains on the shared contrast objective: one window, the contrast loss alone, known speed."""
from __future__ import annotations

import numpy as np
import pytest
import torch


def test_network_overfits_one_window_to_the_fits_depth_error():
    """A small DepthPoseNet trained on one window with the shared objective alone (its speed known, its
    twist predicted; the student's recipe: speed anchor 0.1, gradients clipped to norm 1) reaches the depth
    error of the per-window fit with the same speed (``cmax.fit(speed=)``) on the window's event pixels."""
    from cmax.fitting import fit
    from cmax.metrics import depth_metrics
    from benchmarks.synthetic_windows import preset_window
    from learned.data import Sample, collate, to_item
    from learned.losses import student_loss
    from learned.model import DepthPoseNet, ModelConfig
    from learned.train import _events

    torch.manual_seed(0)
    w = preset_window("slider", 3, width=160, height=120)          # a tuning seed; range 0.4-3 m
    H, W = w.depth.shape
    near_far = (0.4, 3.0)
    batch = collate([to_item(Sample(w.events, w.K, w.depth, w.twist, int(w.events.t[0]), int(w.events.t[-1])),
                             max_events=8000)])
    events = _events(batch, W, H)
    pixels = np.zeros((H, W), bool)
    pixels[np.rint(w.events.y).astype(int).clip(0, H - 1), np.rint(w.events.x).astype(int).clip(0, W - 1)] = True
    pixels &= np.isfinite(w.depth) & (w.depth >= near_far[0]) & (w.depth <= near_far[1])
    fitted = fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=near_far)
    fit_error = depth_metrics(fitted.depth, w.depth, mask=pixels).abs_rel

    net = DepthPoseNet(ModelConfig(width=8, levels=3, min_depth=near_far[0], max_depth=near_far[1],
                                   max_speed=1.0, max_angular_speed=1.0))
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(150):
        optimizer.zero_grad()
        out = net(batch["volume"])
        loss, _ = student_loss(out.inverse_depth, out.twist, events, teacher_inverse_depth=None, speed_weight=0.1)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optimizer.step()
    with torch.no_grad():
        depth = net(batch["volume"]).depth[0, 0].double().numpy()
    net_error = depth_metrics(depth, w.depth, mask=pixels).abs_rel
    assert net_error <= fit_error + 0.02, (net_error, fit_error)
