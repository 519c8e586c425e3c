"""learned.evaluate's masks and objective check, benchmarks.learned_table's rows, spreads, CSV and cache.

Independent expectations: hand-made files whose truth is a constant plane (closed-form errors of a
constant depth), networks whose weights make them predict one known depth and twist, masks built
from the events put in the file.
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from cmax.events import Events

PLANE_M = 3.0                      # the true depth of the hand-made file
FAR_M = 6.5                        # its scene's far limit
TRUE_TWIST = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.1])
W, H = 32, 24
K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
DEPTH_TIMES_US = np.array([100_000, 300_000])
WINDOW_S = 0.1


def plane_file(path, seed: int = 0):
    """A file of ``SyntheticSequence.save``: random events over 0.4 s, the truth a plane at PLANE_M with a
    NaN (sky) column and a column beyond the far limit, a constant twist. Returns (path, events)."""
    from cmax.sim.synthetic import SyntheticSequence

    rng = np.random.default_rng(seed)
    n = 400
    x, y = rng.integers(0, W - 8, n), rng.integers(0, H, n)       # the last 8 columns get no event
    events = Events(x, y, np.sort(rng.integers(0, 400_000, n)), rng.integers(0, 2, n), W, H)
    depth = np.full((2, H, W), PLANE_M, np.float32)
    depth[:, :, 0] = np.nan
    depth[:, :, 1] = FAR_M + 1.0
    poses_t = np.arange(0, 400_001, 5_000)
    poses = np.broadcast_to(np.eye(4), (len(poses_t), 4, 4)).copy()
    poses[:, 0, 3] = TRUE_TWIST[0] * poses_t * 1e-6
    sequence = SyntheticSequence(events, depth, DEPTH_TIMES_US, poses, poses_t,
                                 np.broadcast_to(TRUE_TWIST, (len(poses_t), 6)).copy(), K,
                                 np.arange(0, 400_001, 10_000), {"scene": {"depth_range_m": [1.0, FAR_M]}})
    return sequence.save(path), events


def constant_checkpoint(path, depth_m: float, twist, *, window_us: int = 100_000):
    """A checkpoint whose network predicts ``depth_m`` [m] at every pixel and ``twist`` (6,) for every input."""
    from learned.checkpoint import save_checkpoint
    from learned.config import load_config
    from learned.model import DepthPoseNet

    config = load_config(None, ['data.files=["unused.h5"]', f"data.window_us={window_us}", "data.max_events=3000",
                                "model.width=4", "model.levels=2"], mode="teacher")
    model = DepthPoseNet(config.model)
    lo, hi = 1.0 / config.model.max_depth, 1.0 / config.model.min_depth
    share = (1.0 / depth_m - lo) / (hi - lo)
    scale = np.array([config.model.max_speed] * 3 + [config.model.max_angular_speed] * 3)
    with torch.no_grad():
        for head in model.heads:
            for p in head.parameters():
                p.zero_()
            last = [m for m in head.modules() if isinstance(m, torch.nn.Conv2d)][-1]
            last.bias.fill_(math.log(share / (1 - share)))
        for p in model.pose_out.parameters():
            p.zero_()
        model.pose_out.bias.copy_(torch.from_numpy(np.arctanh(np.asarray(twist) / scale)).float())
    return save_checkpoint(path, {"model": model.state_dict(), "optimizer": {}, "step": 0,
                                  "config": config.to_dict(), "rng": {}})


# -- masks --------------------------------------------------------------------------------------
def test_window_masks_are_valid_truth_and_event_pixels():
    from learned.evaluate import window_masks

    depth = np.full((H, W), 2.0, np.float32)
    depth[0, :] = np.nan
    depth[1, :] = 10.0          # beyond the far limit
    depth[2, :] = 0.0           # no depth
    events = Events(np.array([0, 5, 5, 31]), np.array([0, 3, 3, 23]), np.array([1, 2, 3, 4]),
                    np.array([0, 1, 0, 1]), W, H)
    dense, event = window_masks(depth, events, FAR_M)
    expected = np.ones((H, W), bool)
    expected[:3] = False
    assert np.array_equal(dense, expected)
    hits = np.zeros((H, W), bool)
    hits[3, 5] = hits[23, 31] = True            # (0, 0) has an event but no valid truth
    assert np.array_equal(event, hits)


def test_held_out_windows_event_mask_is_exactly_the_window_events(tmp_path):
    from learned.evaluate import held_out_windows

    path, events = plane_file(tmp_path / "plane.h5")
    windows = held_out_windows(path, 100_000)
    assert [w.sample.t0_us for w in windows] == list(DEPTH_TIMES_US - 50_000)
    for w in windows:
        inside = (events.t >= w.sample.t0_us) & (events.t < w.sample.t1_us)
        hits = np.zeros((H, W), bool)
        hits[events.y[inside], events.x[inside]] = True
        hits[:, :2] = False                      # NaN and beyond-far truth
        assert np.array_equal(w.event, hits)
        assert w.dense[:, 2:].all() and not w.dense[:, :2].any()
        assert not w.event[:, -8:].any() and w.event.sum() > 50


# -- rows, closed forms, spreads, CSV ---------------------------------------------------------------
def test_constant_depth_against_the_closed_form(tmp_path):
    from benchmarks.learned_table import score_all

    path, _ = plane_file(tmp_path / "plane.h5")
    mean_twist = [0.2, 0.0, 0.0, 0.0, 0.0, 0.0]
    exact = score_all([path], {}, constant_depth_m=PLANE_M, mean_twist=mean_twist, window_s=WINDOW_S,
                      baselines=False)
    assert [(r.method, r.mask) for r in exact] == [("constant", "dense"), ("constant", "event")]
    for row in exact:
        assert row.abs_mean_m == 0 and row.rmse_log == 0 and row.coverage == 1 and row.windows == 2
        assert row.v_rms_m_s == pytest.approx(math.sqrt(0.3 ** 2 / 3))
        assert row.omega_rms_deg_s == pytest.approx(math.degrees(math.sqrt(0.1 ** 2 / 3)))
    dense, event = score_all([path], {}, constant_depth_m=4.0, mean_twist=mean_twist, window_s=WINDOW_S,
                             baselines=False)
    for row in (dense, event):
        assert row.abs_mean_m == pytest.approx(1.0) and row.abs_rel == pytest.approx(1 / 3)
        assert row.rmse_log == pytest.approx(math.log(4 / 3)) and row.err_10m == pytest.approx(1.0)
    assert dense.n_pixels == 2 * H * (W - 2)
    assert event.n_pixels < dense.n_pixels


@pytest.fixture
def three_seeds(tmp_path):
    path, _ = plane_file(tmp_path / "plane.h5")
    twists = ([0.5, 0, 0, 0, 0, 0.1], [0.4, 0, 0, 0, 0, 0.1], [0.5, 0.3, 0, 0, 0, 0.1])
    ckpts = [constant_checkpoint(tmp_path / f"net{i}.pt", d, t) for i, (d, t) in
             enumerate(zip((2.5, 3.5, 5.0), twists))]
    return path, ckpts


def test_spreads_over_three_checkpoints(three_seeds, tmp_path):
    from benchmarks.learned_table import markdown_tables, score_all, summarise

    path, ckpts = three_seeds
    rows = score_all([path], {"net": ckpts}, constant_depth_m=PLANE_M, mean_twist=np.zeros(6), baselines=False)
    net = [r for r in rows if r.method == "net" and r.mask == "dense"]
    assert [r.seed for r in net] == ["0", "1", "2"]
    assert [r.abs_mean_m for r in net] == pytest.approx([0.5, 0.5, 2.0], rel=1e-5)
    assert [r.v_rms_m_s for r in net] == pytest.approx([0.0, math.sqrt(0.01 / 3), math.sqrt(0.09 / 3)], abs=1e-6)
    s = summarise(rows, "abs_mean_m")[("net", "plane", "event")]
    assert (s.mean, s.low, s.high, s.count) == pytest.approx((1.0, 0.5, 2.0, 3), rel=1e-5)
    text = "\n".join(markdown_tables(rows))
    assert "| net (3 seeds) | 1.00 (0.50–2.00) / " in text
    assert "| constant | 0.00 / 0.00 |" in text


def test_csv_round_trip(three_seeds, tmp_path):
    from benchmarks.learned_table import CSV_COLUMNS, read_csv, score_all, write_tables

    path, ckpts = three_seeds
    rows = score_all([path], {"net": ckpts}, constant_depth_m=4.0, mean_twist=np.zeros(6), baselines=False)
    md, csv_path = write_tables(rows, tmp_path / "t.md", tmp_path / "t.csv")
    back = read_csv(csv_path)
    assert len(back) == len(rows) == 2 * 4          # 3 seeds + constant, two masks
    for a, b in zip(rows, back):
        for column in CSV_COLUMNS:
            x, y = getattr(a, column), getattr(b, column)
            if isinstance(x, float):
                assert (math.isnan(x) and math.isnan(y)) or y == pytest.approx(x, rel=1e-5), column
            else:
                assert x == y, column
    assert md.read_text().startswith("# ")
    (tmp_path / "bad.csv").write_text("method,sequence\nx,y\n")
    with pytest.raises(ValueError, match="must have the columns"):
        read_csv(tmp_path / "bad.csv")


# -- on a small simulated drive: the baselines, their cache, the objective check ------------------------------
@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """driving_day seed 101 at 64x48: two 0.1 s windows from 0.2 s, the true depth at their middles (~11k events,
    a few pixels of parallax: cmax.fit and EMVS both give depth on it)."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("driving_day", seed=101, width=64, height=48, duration_s=1.0, texture_size=64)
    middles = 0.2 + (np.arange(2) + 0.5) * WINDOW_S
    sequence = simulate_scene(scene, 2 * WINDOW_S + 0.01, EventSimulator(**{**scene.recommended_simulator,
                                                                          "seed": 101}),
                              t0_s=0.2, depth_times_s=middles)
    return sequence.save(tmp_path_factory.mktemp("drive") / "drive.h5")


def test_baselines_are_scored_on_their_coverage_and_cached(drive, tmp_path, monkeypatch):
    import benchmarks.learned_table as table

    cache = tmp_path / "table.baselines.json"
    rows = table.score_all([drive], {}, constant_depth_m=8.0, mean_twist=np.zeros(6), window_s=WINDOW_S, cache=cache)
    by = {(r.method, r.mask): r for r in rows}
    assert set(by) == {(m, k) for m in ("constant", "cmax.fit", "EMVS (GT poses)") for k in ("dense", "event")}
    for method in ("cmax.fit", "EMVS (GT poses)"):
        dense, event = by[(method, "dense")], by[(method, "event")]
        assert 0 < dense.coverage < 1 and 0 < event.coverage <= 1 and np.isfinite(dense.abs_mean_m)
        assert event.n_pixels <= dense.n_pixels
    assert np.isfinite(by[("cmax.fit", "dense")].v_rms_m_s) and np.isnan(by[("EMVS (GT poses)", "dense")].v_rms_m_s)
    # a second run reads the baselines from the cache (refitting would fail here) and gives the same rows
    def refit(*args, **kwargs):
        raise AssertionError("refitted a cached baseline")
    monkeypatch.setattr(table, "fit_windows", refit)
    monkeypatch.setattr(table, "emvs_windows", refit)
    again = table.score_all([drive], {}, constant_depth_m=8.0, mean_twist=np.zeros(6), window_s=WINDOW_S,
                            cache=cache)
    exact = lambda rows: [json.dumps(dataclasses.asdict(r)) for r in rows]  # noqa: E731 (NaN == NaN here)
    assert exact(again) == exact(rows)
    with pytest.raises(AssertionError, match="refitted"):   # another window length is another key
        table.score_all([drive], {}, constant_depth_m=8.0, mean_twist=np.zeros(6), window_s=0.09, cache=cache)


def test_objective_prefers_the_truth_on_a_drive(drive, tmp_path):
    """Picked before looking: the drive above and a network that says 10 m everywhere and straight ahead; the
    shared objective is lowest at the true depth and twist on both windows (on the sparse 64x48 indoor_flying
    windows, 0.2-0.3 px of parallax, it is not: there it prefers the 10 m network)."""
    from learned.evaluate import CANDIDATES, objective_preferences

    ckpt = constant_checkpoint(tmp_path / "c10.pt", 10.0, [0, 0, 0.5, 0, 0, 0])
    result = objective_preferences([drive], ckpt, window_s=WINDOW_S)
    assert len(result.windows) == 2 and sum(result.counts.values()) == 2
    assert result.counts["truth"] == 2
    for w in result.windows:
        assert set(w.values) == set(CANDIDATES) and all(np.isfinite(list(w.values.values())))
        assert w.values["truth"] < w.values["constant depth + true twist"]
        assert w.speed_m_s > 5      # the drive's true speed [m/s], the scale every twist was given


def test_cli_mistakes_are_one_line(tmp_path, capsys):
    from benchmarks.learned_table import main

    path, _ = plane_file(tmp_path / "plane.h5")
    common = ["--data", str(path), "--constant-depth", "3", "--window", "0.1", "--no-baselines"]
    for argv, message in ((common + ["--mean-twist", "1,2"], "6 finite numbers"),
                          (common + ["--mean-twist", "0,0,0,0,0,0", "--method", "net"], "NAME=CKPT"),
                          (common + ["--mean-twist", "0,0,0,0,0,0", "--method", f"net={tmp_path / 'none.pt'}"],
                           "no checkpoint at"),
                          (common, "give --constant-depth and --mean-twist, or --training-data")):
        try:
            status = main(argv)
        except SystemExit as exit:          # argparse's own errors
            status = exit.code
        err = capsys.readouterr().err
        assert status == 2, err
        assert message in err and err.count("\n") == 1, err
    out = tmp_path / "t"
    assert main(common + ["--mean-twist", "0.2,0,0,0,0,0", "--output", str(out)]) == 0
    assert "| constant | 0.00 / 0.00 |" in (tmp_path / "t.md").read_text()
    assert (tmp_path / "t.csv").read_text().count("\n") == 3
    ckpt = constant_checkpoint(tmp_path / "c.pt", 5.0, [0.5, 0, 0, 0, 0, 0])
    assert main(common + ["--training-data", str(path), "--objective-check", str(ckpt), "--output", str(out)]) == 0
    text = (tmp_path / "t.md").read_text()
    assert "twist 0.5, 0, 0, 0, 0, 0.1 (v m/s" in text                          # median 3 m, the mean twist
    assert text.count("| lowest at | windows |") == 2 and "its data term alone (smoothness 0)" in text


def test_training_statistics_of_a_plane(tmp_path):
    from benchmarks.learned_table import training_statistics

    a, _ = plane_file(tmp_path / "a.h5", seed=1)
    b, _ = plane_file(tmp_path / "b.h5", seed=2)
    stats = training_statistics([a, b], pixel_stride=1)
    assert stats.median_depth_m == pytest.approx(PLANE_M)        # the NaN and beyond-far columns left out
    assert stats.mean_twist == pytest.approx(tuple(TRUE_TWIST))
    assert stats.depth_samples == 2 * 2 * H * (W - 2) and stats.twists == 2 * 81


def test_a_network_output_that_overflows_is_one_error_naming_the_checkpoint(tmp_path):
    """Finite weights scaled by 1e30 (not refused as NaN weights) gave `v_pred must be finite, got 27 non-finite
    entries`, naming neither the checkpoint nor the file."""
    from learned.evaluate import evaluate_files

    path, _ = plane_file(tmp_path / "plane.h5")
    good = constant_checkpoint(tmp_path / "good.pt", PLANE_M, TRUE_TWIST)
    assert evaluate_files(good, [path], window_s=WINDOW_S)[0].depth.abs_rel == pytest.approx(0, abs=1e-4)
    ckpt = torch.load(good, weights_only=True)
    ckpt["model"] = {name: tensor * 1e30 for name, tensor in ckpt["model"].items()}
    torch.save(ckpt, tmp_path / "huge.pt")
    with pytest.raises(ValueError, match=r"huge\.pt gives a non-finite output \(NaN or infinite depth or twist\) on "
                                         r"\d of the 2 windows of .*plane\.h5"):
        evaluate_files(tmp_path / "huge.pt", [path], window_s=WINDOW_S)


def test_every_file_is_checked_before_the_network_runs(tmp_path, monkeypatch, capsys):
    """learned.evaluate --data a.h5 b.h5 bare.h5 ran the network over every window of a.h5 and b.h5 (minutes on a
    test set), then refused bare.h5 (no ground truth) and exited 2: the metrics computed were never printed. Each
    file's ground truth is now checked first, and nothing runs when one lacks it."""
    import learned.evaluate as evaluate
    from cmax.io import write_h5

    path, events = plane_file(tmp_path / "plane.h5")
    bare = write_h5(tmp_path / "bare.h5", events)          # the same events, no gt/
    ckpt = constant_checkpoint(tmp_path / "c.pt", PLANE_M, TRUE_TWIST)
    ran = []
    real = evaluate.predict_windows
    monkeypatch.setattr(evaluate, "predict_windows", lambda *a, **k: ran.append(1) or real(*a, **k))
    status = evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), str(bare), "--window", str(WINDOW_S)])
    err = capsys.readouterr().err
    assert status == 2 and f"{bare} has no gt/K nor gt/depth" in err and err.count("\n") == 1, err
    assert ran == []                                        # refused before the network ran on plane.h5
    status = evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), str(tmp_path / "gone.h5")])
    assert status == 2 and f"no such event file: {tmp_path / 'gone.h5'}" in capsys.readouterr().err and ran == []
    # a folder (was named in training's words: "data.files lists h5 files one by one")
    status = evaluate.main(["--checkpoint", str(ckpt), "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "data.files" not in err and ran == [], err
    assert f"{tmp_path} is a folder, not an event file: --data lists h5 files one by one (--data " \
        f"{tmp_path / '*.h5'}: the 2 .h5 files in it)" in err, err
    assert evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), "--window", str(WINDOW_S)]) == 0
    assert ran == [1] and capsys.readouterr().out.startswith("plane: 2 windows")


def test_a_file_listed_twice_or_a_nan_gt_k_is_refused_before_the_network_runs(tmp_path, monkeypatch, capsys):
    """--data a.h5 ./a.h5 scored a.h5 twice without a word (two result lines, its windows counted twice in any
    mean over files); a gt/K holding NaN gave a note that the K is "unlike a camera's" and scored on. Both are
    now refused in one line before the network runs, naming the file (and both positions, or the key)."""
    import shutil

    import h5py

    import learned.evaluate as evaluate

    path, _ = plane_file(tmp_path / "plane.h5")
    other = shutil.copy(path, tmp_path / "other.h5")     # the same bytes, another file: scored once each
    ckpt = constant_checkpoint(tmp_path / "c.pt", PLANE_M, TRUE_TWIST)
    ran = []
    real = evaluate.predict_windows
    monkeypatch.setattr(evaluate, "predict_windows", lambda *a, **k: ran.append(1) or real(*a, **k))
    again = tmp_path / "." / "plane.h5"
    status = evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), str(other), str(again),
                            "--window", str(WINDOW_S)])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and ran == [], err
    assert f"{again} is listed twice in --data (files 1 and 3: {path} and {again})" in err, err
    assert evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), str(other), "--window",
                          str(WINDOW_S)]) == 0
    assert len(ran) == 2 and capsys.readouterr().out.count("2 windows") == 2
    with h5py.File(other, "r+") as file:
        file["gt/K"][0, 0] = np.nan
    ran.clear()
    status = evaluate.main(["--checkpoint", str(ckpt), "--data", str(path), str(other), "--window", str(WINDOW_S)])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and ran == [], err
    assert f"{other}: gt/K holds NaN or infinite values" in err, err


def test_depth_maps_no_better_than_their_own_median_constant_are_noted(tmp_path, monkeypatch):
    """A network whose depth maps score worse than one constant depth printed its metrics without a word (the
    shipped student on a slider scene: abs_rel 2.93, the constant at its own median 1.86): nothing told a trained
    network from an untrained one. A note compares the maps with the constant at their own median (no ground
    truth in it); maps that follow the truth (here a constant: a plane) stay silent."""
    import learned.evaluate as evaluate

    path, _ = plane_file(tmp_path / "plane.h5")
    ckpt = constant_checkpoint(tmp_path / "c.pt", PLANE_M, TRUE_TWIST)
    real = evaluate.predict_windows

    def checkerboard(*args, **kwargs):     # 2 m and 4.5 m about the true 3 m: abs_rel 0.42, its median 0.08
        depth, twist = real(*args, **kwargs)
        rows, cols = np.indices(depth.shape[1:])
        return np.where((rows + cols) % 2 == 0, 2.0, 4.5).astype(np.float32)[None].repeat(len(depth), 0), twist

    (plain,) = evaluate.evaluate_files(ckpt, [path], window_s=WINDOW_S)
    assert plain.depth.abs_rel == pytest.approx(0, abs=1e-4) and not any("constant" in n for n in plain.notes)
    monkeypatch.setattr(evaluate, "predict_windows", checkerboard)
    (board,) = evaluate.evaluate_files(ckpt, [path], window_s=WINDOW_S)
    assert board.depth.abs_rel == pytest.approx((1 / 3 + 1.5 / 3) / 2, rel=0.05)
    notes = [n for n in board.notes if n.startswith("one constant depth, the median of the network's own depths")]
    assert len(notes) == 1 and f"better than the network's {board.depth.abs_rel:.3f}" in notes[0], board.notes


def test_predict_windows_builds_the_volume_the_network_trained_on():
    """A sample with exact sub-pixel positions (Sample.pixels, a calibrated entry's): the network reads the volume
    to_item gives it in training (each event spread bilinearly from its position); before, the volume of the
    events' rounded pixels (another input: the outputs differ)."""
    from learned.data import Sample, to_item
    from learned.evaluate import HeldOutWindow, predict_windows
    from learned.model import DepthPoseNet, ModelConfig

    torch.manual_seed(0)
    model = DepthPoseNet(ModelConfig(width=2, levels=1)).eval()
    rng = np.random.default_rng(4)
    n = 600
    events = Events(rng.integers(0, W, n), rng.integers(0, H, n), np.sort(rng.integers(0, 100_000, n)),
                    rng.integers(0, 2, n), W, H)
    pixels = np.column_stack([events.x, events.y]) + rng.uniform(-0.5, 0.5, (n, 2))
    sample = Sample(events, K, np.full((H, W), PLANE_M, np.float32), TRUE_TWIST, 0, 100_000, pixels=pixels)
    window = HeldOutWindow("s", sample, np.ones((H, W), bool), np.ones((H, W), bool), FAR_M)
    depth, twist = predict_windows(model, [window])
    volume = to_item(sample, max_events=100, bins=model.config.bins, pixels=pixels)["volume"]
    with torch.no_grad():
        expected = model(volume[None])
    np.testing.assert_allclose(depth[0], expected.depth[0, 0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(twist[0], expected.twist[0].numpy(), rtol=1e-6, atol=1e-9)
    rounded, _ = predict_windows(model, [dataclasses.replace(window, sample=dataclasses.replace(sample, pixels=None))])
    assert np.abs(rounded[0] - depth[0]).max() > 1e-4
