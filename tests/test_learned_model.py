"""learned.model and learned.losses: shapes, bounds, closed-form loss values, gradients; evaluate and predict."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from learned.losses import gradient_matching_loss, scale_invariant_loss, student_loss, teacher_loss
from learned.model import DepthPoseNet, ModelConfig


def test_shapes_and_depth_bounds_on_odd_sizes():
    config = ModelConfig(width=4, levels=3, min_depth=1.0, max_depth=20.0, max_speed=2.0, max_angular_speed=1.0)
    net = DepthPoseNet(config)
    out = net(torch.randn(2, 5, 37, 51) * 50)
    assert [tuple(d.shape) for d in out.inverse_depths] == [(2, 1, 37, 51), (2, 1, 19, 26), (2, 1, 10, 13)]
    for d in out.inverse_depths:
        assert float(d.min()) >= 1 / 20.0 and float(d.max()) <= 1.0
    assert out.twist.shape == (2, 6)
    assert float(out.twist[:, :3].abs().max()) <= 2.0 and float(out.twist[:, 3:].abs().max()) <= 1.0
    torch.testing.assert_close(out.depth, 1.0 / out.inverse_depth)


def test_model_rejects_bad_input_and_config():
    with pytest.raises(ValueError, match="volume"):
        DepthPoseNet(ModelConfig(width=4, levels=2))(torch.zeros(1, 3, 16, 16))
    with pytest.raises(ValueError, match="min_depth"):
        ModelConfig(min_depth=5.0, max_depth=1.0)
    with pytest.raises(ValueError, match="width"):
        ModelConfig(width=0)


def test_scale_invariant_loss_closed_form():
    gt = torch.rand(2, 1, 8, 8) * 5 + 1
    mask = torch.ones_like(gt, dtype=torch.bool)
    assert float(scale_invariant_loss(gt * 3.0, gt, mask)) == pytest.approx(0.0, abs=1e-6)  # any global scale
    assert float(scale_invariant_loss(gt * 3.0, gt, mask, variance_weight=0.5)) == pytest.approx(0.5 * math.log(3) ** 2, rel=1e-5)
    # residual +a on half the pixels, -a on the rest: mean(R^2) - mean(R)^2 = a^2
    a = 0.2
    sign = torch.ones_like(gt)
    sign[..., :4] = -1
    assert float(scale_invariant_loss(gt * torch.exp(a * sign), gt, mask)) == pytest.approx(a * a, rel=1e-5)
    # pixels outside the mask do not count
    mask[..., :4] = False
    assert float(scale_invariant_loss(gt * torch.exp(a * sign), gt, mask)) == pytest.approx(0.0, abs=1e-6)


def test_gradient_matching_zero_for_scaled_truth_and_positive_for_edges():
    gt = torch.ones(1, 1, 16, 16) * 4
    gt[..., 8:] = 8
    mask = torch.ones_like(gt, dtype=torch.bool)
    scales = [gt * 2, torch.nn.functional.avg_pool2d(gt * 2, 2)]
    assert float(gradient_matching_loss(scales, gt, mask)) == pytest.approx(0.0, abs=1e-6)
    flat = [torch.full_like(gt, 4.0), torch.full((1, 1, 8, 8), 4.0)]
    assert float(gradient_matching_loss(flat, gt, mask)) > 0.1
    assert float(teacher_loss(flat, gt, mask)) > float(teacher_loss(scales, gt, mask))
    with pytest.raises(ValueError, match="shape"):
        gradient_matching_loss([gt[0]], gt, mask)
    with pytest.raises(TypeError, match="bool"):
        scale_invariant_loss(gt, gt, mask.float())


def test_teacher_loss_gradcheck():
    gt = torch.rand(1, 1, 6, 6, dtype=torch.float64) * 3 + 1
    mask = torch.rand(1, 1, 6, 6) > 0.2
    pred = (torch.rand(1, 1, 6, 6, dtype=torch.float64) * 3 + 1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: teacher_loss([p], gt, mask, variance_weight=0.85), (pred,))


def test_student_loss_is_contrast_plus_weighted_l1():
    from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows
    from cmax.synthetic_windows import make_window

    w = make_window("slider", 2, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30)
    events = EventWindows.from_events(w.events, w.K, max_events=2000)
    rho = torch.full((1, 1, 48, 64), 0.3)
    teacher = torch.full((1, 1, 48, 64), 0.5)
    twist = torch.as_tensor(w.twist, dtype=torch.float32)[None]
    contrast = float(SHARED_OBJECTIVE(events, DepthMotion(rho, twist)).mean())
    loss, terms = student_loss(rho, twist, events, teacher_inverse_depth=teacher)
    assert float(loss) == pytest.approx(contrast + 0.4 * 0.2, rel=1e-5)
    assert terms["l1_teacher"] == pytest.approx(0.2)
    alone, terms = student_loss(rho, twist, events, teacher_inverse_depth=None)
    assert float(alone) == pytest.approx(contrast) and "l1_teacher" not in terms


def test_evaluate_and_predict_on_a_trained_checkpoint(tmp_path):
    """A teacher trained for a few steps: evaluate prints metrics equal to cmax.metrics on its own predictions."""
    from cmax.metrics import depth_metrics
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene
    from learned.config import load_config
    from learned.data import H5WindowDataset
    from learned.evaluate import evaluate_files, load_model
    from learned.predict import predict_file
    from learned.train import Trainer

    scene = make_scene("indoor_flying", seed=7, width=40, height=30, duration_s=1.0, texture_size=64)
    path = simulate_scene(scene, 0.4, EventSimulator(**{**scene.recommended_simulator, "seed": 7}),
                          depth_rate_hz=20).save(tmp_path / "s.h5")
    config = load_config(None, [f'data.files=["{path}"]', "data.window_us=100000", "data.max_events=500",
                                "model.width=4", "model.levels=2", "train.batch_size=2", "train.steps=2",
                                f"train.out={tmp_path / 'run'}"], mode="teacher")
    Trainer(config, progress=False).run()
    ckpt = tmp_path / "run" / "last.pt"
    (report,) = evaluate_files(ckpt, [path])
    model, _ = load_model(ckpt)
    ds = H5WindowDataset([path], window_us=100_000, max_events=1000, min_events=10)
    preds = np.stack([model(ds[i]["volume"][None]).depth[0, 0].detach().numpy() for i in range(len(ds))])
    gts = np.stack([ds.sample(i).depth for i in range(len(ds))])
    expected = depth_metrics(preds, gts, max_depth=6.5)
    assert report.windows == len(ds)
    assert report.depth.abs_mean == pytest.approx(expected.abs_mean, rel=1e-5)
    assert report.motion is not None
    n = predict_file(ckpt, path, tmp_path / "pred", progress=False)   # consecutive windows from the first event
    from cmax.io import H5Reader
    from cmax.representations import voxel_grid
    with H5Reader(path) as reader:
        assert n == (reader.t_end - reader.t_start) // 100_000
        first = reader.window(reader.t_start, reader.t_start + 100_000)
    saved = np.load(tmp_path / "pred" / "window_00000.npz")
    expected_depth = model(torch.from_numpy(voxel_grid(first, 5))[None]).depth[0, 0].detach().numpy()
    np.testing.assert_allclose(saved["depth"], expected_depth, rtol=1e-5)
    assert (tmp_path / "pred" / "twists.csv").read_text().count("\n") == n + 1
    import cv2
    picture = cv2.imread(str(tmp_path / "pred" / "window_00000.png"))   # the map, its title and colour bar
    assert picture.shape[1] > saved["depth"].shape[1] + 30 and picture.shape[0] > saved["depth"].shape[0]
