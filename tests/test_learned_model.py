"""learned.model and learned.losses: shapes, bounds, closed-form loss values, gradients; evaluate and predict."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from learned.losses import gradient_matching_loss, scale_invariant_loss, student_loss, teacher_loss
from learned.model import DepthPoseNet, ModelConfig


@pytest.mark.parametrize("block, norm, space_to_depth", [
    ("dense", "group", False), ("separable", "group", False), ("separable", "none", False), ("dense", "none", False),
    ("dense", "group", True), ("separable", "group", True), ("separable", "none", True)])
def test_shapes_and_depth_bounds_on_odd_sizes(block, norm, space_to_depth):
    config = ModelConfig(width=4, levels=3, min_depth=1.0, max_depth=20.0, max_speed=2.0, max_angular_speed=1.0,
                         block=block, norm=norm, space_to_depth=space_to_depth)
    net = DepthPoseNet(config)
    net.pose_out.weight.data.normal_(0, 10.0)   # a saturating pose head: the bounds must still hold
    with torch.no_grad():
        out = net(torch.randn(2, 5, 37, 51) * 50)
    assert [tuple(d.shape) for d in out.inverse_depths] == [(2, 1, 37, 51), (2, 1, 19, 26), (2, 1, 10, 13)]
    for d in out.inverse_depths:
        assert float(d.min()) >= 1 / 20.0 and float(d.max()) <= 1.0
        assert float(d.max() - d.min()) > 0   # the input reaches the output
    assert out.twist.shape == (2, 6)
    assert float(out.twist[:, :3].abs().max()) <= 2.0 and float(out.twist[:, 3:].abs().max()) <= 1.0
    assert float(out.twist.abs().min()) > 0
    torch.testing.assert_close(out.depth, 1.0 / out.inverse_depth)


def test_block_kinds_build_the_layers_they_name():
    dense, separable = DepthPoseNet(ModelConfig(width=8)), DepthPoseNet(ModelConfig(width=8, block="separable"))
    assert [tuple(m.weight.shape) for m in dense.stem if isinstance(m, torch.nn.Conv2d)] == [(8, 5, 3, 3), (8, 8, 3, 3)]
    # depthwise 3x3 (one filter per input channel) then pointwise 1x1, twice
    assert [(tuple(m.weight.shape), m.groups) for m in separable.stem if isinstance(m, torch.nn.Conv2d)] == [
        ((5, 1, 3, 3), 5), ((8, 5, 1, 1), 1), ((8, 1, 3, 3), 8), ((8, 8, 1, 1), 1)]
    plain = DepthPoseNet(ModelConfig(width=8, norm="none"))
    assert not any(isinstance(m, torch.nn.GroupNorm) for m in plain.modules())
    assert plain.stem[0].bias is not None and dense.stem[0].bias is None   # a bias only where no norm follows
    count = lambda net: sum(p.numel() for p in net.parameters())
    assert count(separable) < count(dense) / 2
    # space to depth: 2x2 pixels x 5 bins in, one level fewer, a 4-channel head unfolded to full resolution
    folded = DepthPoseNet(ModelConfig(width=8, levels=3, space_to_depth=True))
    assert folded.stem[0].weight.shape == (8, 20, 3, 3) and len(folded.down) == len(folded.heads) == 2
    assert folded.full_head.weight.shape == (4, 8, 3, 3) and not hasattr(dense, "full_head")


@pytest.mark.parametrize("config", [ModelConfig(width=4, levels=2), ModelConfig.fast(width=4, levels=2)])
def test_channels_last_is_a_layout_not_a_different_network(config):
    fast, plain = DepthPoseNet(config), DepthPoseNet(config, channels_last=False)
    assert fast.stem[0].weight.is_contiguous(memory_format=torch.channels_last)
    assert not plain.stem[0].weight.is_contiguous(memory_format=torch.channels_last)
    plain.load_state_dict(fast.state_dict())
    volume = torch.randn(2, 5, 19, 27)
    with torch.no_grad():
        a, b = fast(volume), plain(volume)
    for x, y in zip(a.inverse_depths, b.inverse_depths):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(a.twist, b.twist, rtol=1e-5, atol=1e-6)


def test_space_to_depth_full_resolution_output_unfolds_the_head():
    """The finest inverse depth at pixel (2i + a, 2j + b) is the head's channel 2a + b at (i, j)."""
    net = DepthPoseNet(ModelConfig(width=4, levels=2, space_to_depth=True, min_depth=1.0, max_depth=10.0))
    captured = {}
    net.full_head.register_forward_hook(lambda module, args, output: captured.update(logits=output))
    with torch.no_grad():
        out = net(torch.randn(1, 5, 12, 16))
    logits = captured["logits"][0]   # (4, 6, 8)
    expected = 0.1 + 0.9 * torch.sigmoid(logits)
    for a in range(2):
        for b in range(2):
            torch.testing.assert_close(out.inverse_depth[0, 0, a::2, b::2], expected[2 * a + b])


def test_model_rejects_bad_input_and_config():
    with pytest.raises(ValueError, match="volume"):
        DepthPoseNet(ModelConfig(width=4, levels=2))(torch.zeros(1, 3, 16, 16))
    with pytest.raises(ValueError, match="min_depth"):
        ModelConfig(min_depth=5.0, max_depth=1.0)
    with pytest.raises(ValueError, match="width"):
        ModelConfig(width=0)
    with pytest.raises(ValueError, match="model.block must be one of"):
        ModelConfig(block="mobile")
    with pytest.raises(ValueError, match="model.norm must be one of"):
        ModelConfig(norm="batch")
    with pytest.raises(ValueError, match="GroupNorm"):   # 12 channels in 8 groups
        ModelConfig(width=12)
    with pytest.raises(ValueError, match="space_to_depth"):
        ModelConfig(space_to_depth=1)
    assert DepthPoseNet(ModelConfig(width=12, norm="none", levels=1))(torch.zeros(1, 5, 8, 8)).twist.shape == (1, 6)


def test_config_files_reach_the_new_fields_and_name_bad_ones():
    from learned.config import load_config

    config = load_config(None, ['model.block="separable"', "model.norm=none", "model.width=8"])
    assert (config.model.block, config.model.norm, config.model.width) == ("separable", "none", 8)
    assert ModelConfig.fast() == ModelConfig(space_to_depth=True)
    assert ModelConfig.fast(max_depth=10.0).max_depth == 10.0
    with pytest.raises(TypeError, match="model.block must be a string"):
        load_config(None, ["model.block=3"])
    with pytest.raises(TypeError, match="model.space_to_depth must be true or false"):
        load_config(None, ["model.space_to_depth=1"])
    assert load_config(None, ["model.space_to_depth=true"]).model.space_to_depth is True
    with pytest.raises(ValueError, match="model.block must be one of"):
        load_config(None, ["model.block=resnet"])


# The original network (before ModelConfig.block / .norm), width 2, levels 1: its parameters in order and
# the outputs that its code (commit 757fe8a) gave for the weights and input below.
_OLD_KEYS = [("stem.0.weight", (2, 5, 3, 3)), ("stem.1.weight", (2,)), ("stem.1.bias", (2,)),
             ("stem.3.weight", (2, 2, 3, 3)), ("stem.4.weight", (2,)), ("stem.4.bias", (2,)),
             ("down.0.0.weight", (4, 2, 3, 3)), ("down.0.1.weight", (4,)), ("down.0.1.bias", (4,)),
             ("down.0.3.weight", (4, 4, 3, 3)), ("down.0.4.weight", (4,)), ("down.0.4.bias", (4,)),
             ("up.0.0.weight", (2, 6, 3, 3)), ("up.0.1.weight", (2,)), ("up.0.1.bias", (2,)),
             ("up.0.3.weight", (2, 2, 3, 3)), ("up.0.4.weight", (2,)), ("up.0.4.bias", (2,)),
             ("heads.0.weight", (1, 2, 3, 3)), ("heads.0.bias", (1,)), ("pose.0.weight", (4, 4, 3, 3)),
             ("pose.0.bias", (4,)), ("pose_out.weight", (6, 4)), ("pose_out.bias", (6,))]
_OLD_INVERSE_DEPTH_ROWS = [[1.0327216386795044, 1.0052361488342285, 1.0205340385437012, 1.0455844402313232],
                           [1.0701361894607544, 1.106982946395874, 1.1215777397155762, 1.1065514087677002]]
_OLD_INVERSE_DEPTH_SUM = 64.69664001464844
_OLD_TWIST = [-7.493375778198242, -6.484403133392334, -3.9564170837402344, -0.5053828954696655,
              1.4670695066452026, 0.64588862657547]


def test_old_config_checkpoints_load_and_compute_what_they_did(tmp_path):
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config
    from learned.evaluate import load_model

    fill = lambda shape, k: (torch.sin(torch.arange(math.prod(shape), dtype=torch.float64) * 0.7 + k)
                             .reshape(shape).float() * 0.5)
    weights = {name: fill(shape, k) for k, (name, shape) in enumerate(_OLD_KEYS)}
    config = Config(model=ModelConfig(width=2, levels=1)).to_dict()
    for key in ("block", "norm", "space_to_depth", "pose_cells", "odd_twist"):   # as written before these fields existed
        del config["model"][key]
    save_checkpoint(tmp_path / "old.pt", {"model": weights, "optimizer": {}, "step": 0, "config": config,
                                          "rng": rng_state()})
    model, loaded = load_model(tmp_path / "old.pt")
    assert (loaded["model"]["block"], loaded["model"]["norm"], loaded["model"]["space_to_depth"],
            loaded["model"]["odd_twist"]) == ("dense", "group", False, False)
    x = (torch.cos(torch.arange(5 * 7 * 9, dtype=torch.float64) * 0.3).reshape(1, 5, 7, 9).float() * 3)
    with torch.no_grad():
        out = model(x)
    np.testing.assert_allclose(out.inverse_depth[0, 0, :2, :4].numpy(), _OLD_INVERSE_DEPTH_ROWS, rtol=1e-5)
    assert float(out.inverse_depth.sum()) == pytest.approx(_OLD_INVERSE_DEPTH_SUM, rel=1e-5)
    np.testing.assert_allclose(out.twist[0].numpy(), _OLD_TWIST, rtol=1e-4, atol=1e-5)


def test_the_shipped_networks_give_a_window_played_backwards_the_negated_twist():
    """A window played backwards (learned.data.reverse_time: the physics of time reversal, the twist negated) must
    get -twist: the student trained with reverse_time on the plain pose head gave one v for a window and its
    reverse (its drives' translation 177 deg off on one run). The recipe's network (odd_twist) gives exactly
    -twist for any weights; the plain pose head does not; the depth is left as it is."""
    from benchmarks.synthetic_windows import make_window
    from learned.config import load_config
    from learned.data import Sample, reverse_time, to_item

    root = Path(__file__).resolve().parents[1] / "learned" / "configs"
    models = {mode: load_config(root / f"{mode}.toml", ["train.val_every=0", "train.teacher=t.pt"]).model
              for mode in ("teacher", "finetune", "student")}
    assert all(model.odd_twist for model in models.values())
    w = make_window("slider", 2, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30)
    sample = Sample(w.events, w.K, w.depth, w.twist, int(w.events.t[0]), int(w.events.t[-1]))
    volumes = torch.stack([to_item(s, max_events=1000)["volume"] for s in (sample, reverse_time(sample))])
    twists, depths = {}, {}
    for odd in (True, False):
        torch.manual_seed(0)
        net = DepthPoseNet(dataclasses.replace(models["student"], width=4, levels=2, odd_twist=odd)).eval()
        net.pose_out.weight.data.normal_(0, 0.3)   # the zero-initialised head would give 0 for both
        with torch.no_grad():
            out = net(volumes)
        twists[odd], depths[odd] = out.twist, out.inverse_depth
    assert float(twists[True][0].abs().max()) > 0.05
    torch.testing.assert_close(twists[True][1], -twists[True][0], rtol=0, atol=1e-6)
    assert float((twists[False][1] + twists[False][0]).abs().max()) > 0.01   # the plain head: no such symmetry
    torch.testing.assert_close(depths[True], depths[False], rtol=0, atol=0)   # same weights, same depth


def test_the_odd_twist_is_taken_before_the_tanh_so_a_shared_offset_cannot_saturate_it():
    """The odd head's twist is ``s * tanh((h(V) - h(R V)) / 2)``: whatever the two passes share (here the linear
    layer's bias, set to 30, as a drifting common mode would) cancels before the tanh, so the twist and its gradient
    equal those with no bias. Taken after the tanh (the first odd head), tanh(30 + d) - tanh(30 - d) is 0 to float
    precision: a twist of exactly 0 with no gradient, what 2 of 3 recipe runs at 160x120 ended in."""
    torch.manual_seed(0)
    net = DepthPoseNet(ModelConfig(width=4, levels=2, odd_twist=True)).eval()
    net.pose_out.weight.data.normal_(0, 0.3)
    volume = torch.randn(2, 5, 32, 48)
    net.pose_out.bias.data.zero_()
    plain = net(volume).twist
    net.pose_out.bias.data.fill_(30.0)
    shifted = net(volume).twist
    assert float(plain.abs().max()) > 0.05
    torch.testing.assert_close(shifted, plain, rtol=1e-3, atol=1e-4)   # float32: 30 + h loses ~1e-6 of h
    (grad,) = torch.autograd.grad(shifted.square().sum(), net.pose_out.weight)
    assert float(grad.abs().max()) > 1e-3


def test_odd_twist_must_be_a_bool():
    with pytest.raises(ValueError, match=r"model\.odd_twist must be true or false, got 'yes'"):
        ModelConfig(odd_twist="yes")


@pytest.mark.parametrize("config, factor", [(ModelConfig.fast(levels=2), 5),
                                            (ModelConfig(width=8, levels=2, block="separable"), 5),
                                            (ModelConfig(width=8, levels=2, block="separable", norm="none"), 2)])
def test_fast_net_learns_a_fixed_depth_map(config, factor):
    """Teacher loss on one fixed volume and depth map: 60 Adam steps cut it ``factor`` times (no norm learns slower)."""
    torch.manual_seed(0)
    rows, cols = torch.meshgrid(torch.linspace(0, 1, 24), torch.linspace(0, 1, 32), indexing="ij")
    depth = (1.0 + 3.0 * cols + 2.0 * (rows > 0.5)).expand(2, 1, 24, 32)   # a ramp and a step [m]
    volume = torch.stack([torch.sin(7 * cols + k) * depth[0, 0] for k in range(5)])[None].expand(2, -1, -1, -1)
    mask = torch.ones_like(depth, dtype=torch.bool)
    net = DepthPoseNet(config)
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        out = net(volume)
        loss = teacher_loss(tuple(1.0 / d for d in out.inverse_depths), depth, mask)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / factor


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
    from benchmarks.synthetic_windows import make_window
    from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows

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
    # the pictures of one run share one colour scale: the percentiles of all its windows' depths (these maps are
    # small enough to be pooled whole), with its colour bar in metres
    import json

    import cv2

    from cmax import viz
    from learned.predict import window_picture

    depths = [np.load(tmp_path / "pred" / f"window_{k:05d}.npz")["depth"] for k in range(n)]
    scale = viz.DepthScale.from_depths(depths)
    assert json.loads((tmp_path / "pred" / "summary.json").read_text())["depth_range_m"] == [scale.near, scale.far]
    picture = cv2.imread(str(tmp_path / "pred" / "window_00000.png"))
    origin = int(saved["t0_us"])   # the first window starts at the first event, the title's origin
    panel = window_picture(saved["depth"], scale, f"window 0, {(int(saved['t0_us']) - origin) * 1e-6:.3f}-"
                           f"{(int(saved['t1_us']) - origin) * 1e-6:.3f} s, depth [m]")
    assert np.array_equal(picture, panel)


@pytest.mark.parametrize("n, bins, same_time", [(0, 5, False), (1, 5, False), (7, 5, True), (5000, 5, False),
                                                (5000, 1, False), (5000, 3, False)])
def test_event_volume_equals_voxel_grid(n, bins, same_time):
    from cmax.events import Events
    from cmax.representations import voxel_grid
    from learned.volume import event_volume

    rng = np.random.default_rng(n + bins)
    t = np.full(n, 1_000_000) if same_time else np.sort(rng.integers(10**12, 10**12 + 166_500, n))
    events = Events(rng.integers(0, 37, n), rng.integers(0, 23, n), t, rng.integers(0, 2, n), width=37, height=23)
    volume = event_volume(events, bins)
    assert volume.shape == (bins, 23, 37) and volume.dtype == np.float32
    np.testing.assert_allclose(volume, voxel_grid(events, bins), atol=2e-6)
    if n:   # each event's weight 1 in total, signed by polarity
        assert float(volume.sum()) == pytest.approx(float(2 * events.p.sum() - n), abs=1e-3)


def test_event_volume_doc_example_and_bad_input():
    from cmax.events import Events
    from learned.volume import event_volume

    ev = Events([0, 1, 1], [0, 0, 0], [0, 50, 100], [1, 1, 0], width=2, height=1)
    assert event_volume(ev, bins=3)[:, 0].tolist() == [[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]
    with pytest.raises(TypeError, match="Events"):
        event_volume(ev.to_torch())
    with pytest.raises(TypeError, match=r"events must be cmax\.Events, got ndarray \(a structured array with fields "
                                        r"\['x', 'y', 't', 'p'\]\): cmax\.Events\.from_structured"):
        event_volume(ev.to_structured())            # tonic's events (was: `must be cmax.events.Events, got ndarray`)
    with pytest.raises(ValueError, match="bins"):
        event_volume(ev, bins=0)


def test_evaluate_notes_a_camera_unlike_the_one_the_network_was_trained_with(tmp_path, capsys):
    """The shipped network (its card: the trained sensor and K) evaluated on a 40x30 file: the report and the
    command line say that the sensor differs and by how much the focal length scales its depth, as cmax depth
    does."""
    import json

    import h5py

    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene
    from learned.evaluate import evaluate_files, main
    from learned.pretrained import shipped_checkpoint

    scene = make_scene("indoor_flying", seed=7, width=40, height=30, duration_s=1.0, texture_size=64)
    path = simulate_scene(scene, 0.4, EventSimulator(**{**scene.recommended_simulator, "seed": 7}),
                          depth_rate_hz=20).save(tmp_path / "s.h5")
    checkpoint = shipped_checkpoint()
    card = json.loads(checkpoint.with_suffix(".json").read_text())
    with h5py.File(path, "r") as file:
        fx = float(file["gt/K"][0, 0])
    (report,) = evaluate_files(checkpoint, [path])
    assert any(f"trained on a {card['size'][0]}x{card['size'][1]} sensor, this file is 40x30" in n for n in report.notes)
    assert any(f"predicted x {fx / card['K'][0]:.3g}" in n for n in report.notes)
    assert main(["--checkpoint", str(checkpoint), "--data", str(path)]) == 0
    err = capsys.readouterr().err
    assert err.count("learned.evaluate: note: s: ") == len(report.notes) >= 2
