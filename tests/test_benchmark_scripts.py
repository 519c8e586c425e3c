"""The glue between benchmark scripts: the speed section reuses the accuracy benchmark's runs (the fits
themselves are timed by the scripts, not here)."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import benchmarks.accuracy_cmax as accuracy_cmax
import benchmarks.accuracy_presets as presets
from benchmarks.real_cmax import _drive_summary
from benchmarks.speed_cmax import fit_seconds


def test_speed_section_calls_the_accuracy_runs_with_window_and_seed(monkeypatch):
    calls = []

    def fake_run(model):
        def run(window, seed):
            calls.append((model, window, seed))
            return {"seconds": float(seed)}
        return run

    monkeypatch.setattr(accuracy_cmax, "RUNS", {m: fake_run(m) for m in accuracy_cmax.RUNS})
    monkeypatch.setattr(accuracy_cmax, "windows", lambda model, seed, cache: f"{model}-{seed}")
    seconds = fit_seconds(2)
    assert seconds == {m: [100.0, 101.0] for m in ("flow", "rotation", "depth", "se3")}
    assert ("se3", "se3-101", 101) in calls and len(calls) == 4 * 3   # one warm-up + two windows per model


def test_scored_pixels_keep_the_mask_with_ground_truth_inside_the_range():
    truth = np.array([[1.0, 5.0, np.nan], [90.0, 2.0, 3.0]], np.float32)
    result = SimpleNamespace(mask=np.array([[True, True, True], [True, False, True]]),
                             depth=np.array([[1.5, 5.0, 1.0], [1.0, 2.0, 6.0]], np.float32))
    assert accuracy_cmax.scored_pixels(result, truth).tolist() == [[True, True, False], [True, False, True]]
    in_range = accuracy_cmax.scored_pixels(result, truth, (1.5, 80.0))
    assert in_range.tolist() == [[False, True, False], [False, False, True]]
    # abs_rel over the two scored pixels: |5-5|/5 and |6-3|/3
    assert abs(accuracy_cmax.abs_rel(result, truth, (1.5, 80.0)) - 0.5) < 1e-6
    # the half with the smaller depth spread: of the 4 scored pixels (spreads 0.3, 0.1, 0.0, 0.2), the
    # pixels (1, 0) and (0, 1), errors |1 - 90| / 90 and 0
    result.depth_spread = np.array([[0.3, 0.1, 0.0], [0.0, 0.0, 0.2]], np.float32)
    assert abs(accuracy_cmax.abs_rel_half(result, truth) - (89 / 90 + 0.0) / 2) < 1e-6


def test_abs_rel_recorded_scores_the_pixels_the_events_were_recorded_at():
    from cmax.events import Events

    truth = np.array([[1.0, 5.0, np.nan], [90.0, 2.0, 3.0]], np.float32)
    result = SimpleNamespace(mask=np.zeros((2, 3), bool),   # the mask plays no part
                             depth=np.array([[1.5, 5.0, 1.0], [1.0, 2.0, 6.0]], np.float32))
    events = Events(np.array([0, 0, 2, 2, 1]), np.array([0, 0, 0, 1, 1]), np.arange(5), np.ones(5, int), 3, 2)
    # recorded pixels (0, 0), (0, 2) (no truth), (1, 2), (1, 1): errors 0.5, 1.0 and 0
    assert abs(accuracy_cmax.abs_rel_recorded(result, events, truth) - 0.5) < 1e-6
    assert abs(accuracy_cmax.abs_rel_recorded(result, events, truth, (1.5, 80.0)) - 0.5) < 1e-6  # 1.0 and 0


def test_accuracy_fits_get_the_room_depth_range_and_the_default_range_rows_do_not(monkeypatch):
    calls = []
    monkeypatch.setattr(accuracy_cmax, "run_depth", lambda w, **s: calls.append(("depth", s)) or {})
    monkeypatch.setattr(accuracy_cmax, "run_se3", lambda w, omega=None, **s: calls.append(("se3", s)) or {})
    window = SimpleNamespace(twist=np.zeros(6))
    for model in ("depth", "depth_default_range", "se3", "se3_default_range", "se3_gyro", "se3_gyro_bias"):
        accuracy_cmax.RUNS[model](window, 100)
    room = {"depth_range": (1.0, 6.5)}   # the indoor_flying preset's stated range
    judged = {"verdict": True}
    assert calls == [("depth", room), ("depth", {}), ("se3", {**judged, **room}), ("se3", judged),
                     ("se3", {**judged, **room}), ("se3", {**judged, **room})]


def test_the_accuracy_report_gives_the_figures_over_the_windows_the_fit_called_ok():
    results = [{"abs_rel": a, "seconds": 1.0, "verdict": v}
               for a, v in [(0.1, "ok"), (0.9, "low_parallax"), (0.3, "ok"), (0.7, "ambiguous"), (0.2, "ok")]]
    text = accuracy_cmax.summarise({"se3": results, "depth": [{"abs_rel": 0.05}] * 5}, list(range(100, 105)), 1.0)
    # all five windows: median 0.3, p90 0.82 (numpy's linear interpolation between 0.7 and 0.9)
    assert "| se3 | abs_rel | 0.300 | 0.820 | <= 0.2 | no / no |" in text
    assert "| se3 | ambiguous 1, low_parallax 1, ok 3 |" in text
    # the three ok windows (0.1, 0.2, 0.3): median 0.2, p90 0.28
    assert "| se3 (ok, 3 of 5) | abs_rel | 0.200 | 0.280 | <= 0.2 | yes / no |" in text
    assert "- se3 seed 101: abs_rel 0.900, seconds 1.000, verdict low_parallax" in text
    assert "depth (ok" not in text   # no verdicts, no such rows


def test_presets_benchmark_fits_every_preset_with_its_depth_range(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(presets, "preset_window", lambda preset, seed, cache: (preset, seed))
    monkeypatch.setattr(presets, "run_depth", lambda w, **s: calls.append(("depth", w, s)) or {"abs_rel": 0.1})
    monkeypatch.setattr(presets, "run_se3", lambda w, **s: calls.append(("se3", w, s)) or {"abs_rel": 0.2})
    monkeypatch.setattr(presets, "run_rotation",
                        lambda w: calls.append(("rotation", w, {})) or {"omega_rel_error": 0.01})
    monkeypatch.setattr(presets, "figure_row", lambda preset, window, depth_range: np.zeros((4, 4, 3), np.uint8))
    monkeypatch.setattr(presets, "RESULTS", tmp_path)
    assert presets.main(["--seeds", "100-101", "--presets", "rotation,driving_day"]) == 0
    # the rotation preset does not translate: rotation model only; driving gets its stated range, clipped
    assert [c[0] for c in calls if c[1][0] == "rotation"] == ["rotation", "rotation"]
    assert ("se3", ("driving_day", 101), {"depth_range": (1.5, accuracy_cmax.FAR_CLIP_M)}) in calls
    assert ("se3", ("driving_day", 101), {"depth_range": (1.5, accuracy_cmax.FAR_CLIP_M), "zero_rotation_start": True}) \
        in calls
    text = (tmp_path / "accuracy_presets.md").read_text()
    assert "| driving_day | 1.5-80 | se3 | abs_rel | 0.200 | 0.200 |" in text
    assert "| rotation | 0.8-6 | rotation | omega_rel_error | 0.010 | 0.010 |" in text
    assert (tmp_path / "accuracy_presets.png").exists()


def test_presets_figure_only_draws_the_figure_of_the_moving_presets_and_writes_no_table(monkeypatch, tmp_path):
    import pytest

    drawn = []
    monkeypatch.setattr(presets, "preset_window", lambda preset, seed, cache: (preset, seed))
    monkeypatch.setattr(presets, "measure", lambda *a: pytest.fail("--figure-only must not measure"))
    monkeypatch.setattr(presets, "figure_row",
                        lambda preset, window, depth_range: drawn.append(window) or np.zeros((4, 4, 3), np.uint8))
    monkeypatch.setattr(presets, "RESULTS", tmp_path)
    assert presets.main(["--figure-only", "--quick", "--presets", "rotation,driving_day"]) == 0
    assert drawn == [("driving_day", 100)]                # the rotation preset does not translate: no row
    assert [p.name for p in tmp_path.iterdir()] == ["accuracy_presets_quick.png"]
    with pytest.raises(SystemExit):                       # nothing to draw is refused, not an empty picture
        presets.main(["--figure-only", "--presets", "rotation"])


def test_drive_summary_is_computed_from_the_fits():
    def result(v, omega_deg, verdict="ok"):
        return SimpleNamespace(v=np.asarray(v, float), omega=np.radians(omega_deg),
                               verdict=SimpleNamespace(value=verdict))

    # seed 1 is 78.9 deg from +z (cos = 0.2 / |(0, 1, 0.2)|), seed 0 cos^-1(1 / |(0.1, 0, 1)|) = 5.7 deg
    default = {0: result([0.1, 0, 1], [0, 0, 0]), 1: result([0, 1, 0.2], [134, 2, 0], "ambiguous")}
    others = {("zrs", 0): result([0, 0.1, 1], [0, -3, 0]), ("zrs", 1): result([1, 0, 0.1], [0, 5, 0]),
              ("held", 0): result([0, 0, 1], [0, 0, 0])}
    text = _drive_summary(default, others)
    assert text.startswith("The default fit is within 15 deg of forward at 1 of 2 fit seeds; the farthest (seed 1) "
                           "ends 79 deg from +z with a pitch rate of +134 deg/s, verdict ambiguous.")
    assert text.endswith("Fits off by more: zrs.")
    default[1] = result([0, 0, 1], [1, -2, 0])
    del others["zrs", 1]
    assert _drive_summary(default, others) == ("The default fit is within 15 deg of forward at 2 of 2 fit seeds. "
                                               "Every other fit is within it.")


def test_preset_windows_and_constant_twist_windows_are_cached_apart(monkeypatch):
    """accuracy_cmax's 'rotation' windows (constant twist, 0.05 s) are not the 'rotation' preset's windows."""
    keys = []
    monkeypatch.setattr(presets, "cached", lambda cache, key, make: keys.append(key))
    monkeypatch.setattr(accuracy_cmax, "cached", lambda cache, key, make: keys.append(key))
    for model in ("rotation", "depth"):
        accuracy_cmax.windows(model, 100, None)
    for preset in ("rotation", "indoor_flying", "slider"):
        presets.preset_window(preset, 100, None)
    assert len(set(keys)) == len(keys) == 5


def test_ecd_slider_emvs_figure_has_a_legend_a_colour_bar_and_no_white_no_estimate():
    """The EMVS figure drew "no estimate" white (next to the near end of the colour map) and
    its events without an ON/OFF legend."""
    from types import SimpleNamespace

    from benchmarks.ecd_slider_emvs import figure
    from cmax import viz
    from cmax.camera import Camera
    from conftest import random_events

    width, height = 96, 72
    mask = np.zeros((height, width), bool)
    mask[20:40, 30:60] = True
    result = SimpleNamespace(t_ref_us=50_000, confidence=np.random.default_rng(0).random((height, width)),
                             depth=np.full((height, width), 1.0, np.float32), mask=mask, depth_range=(0.5, 2.0))
    camera = Camera(np.array([[80.0, 0, 48], [0, 80.0, 36], [0, 0, 1]]), width, height)
    frame = np.full((height, width), 128, np.uint8)
    picture = figure(frame, random_events(2000, width=width, height=height, t_span_us=100_000, seed=1),
                     result, camera)
    pixels = picture.reshape(-1, 3)
    hatch = (pixels == viz.NO_DEPTH_BGR).all(axis=1) | (pixels == viz.NO_DEPTH_HATCH_BGR).all(axis=1)
    assert hatch.sum() >= (~mask).sum()                       # every pixel without depth is hatched
    title_rows = picture[: picture.shape[0] - height].reshape(-1, 3)
    assert (title_rows == viz.ON_BGR).all(axis=1).sum() >= 25   # the ON/OFF legend
    assert (title_rows == viz.OFF_BGR).all(axis=1).sum() >= 25


def test_accuracy_depth_figure_has_a_legend_a_colour_bar_of_the_ground_truth_scale_and_a_hatch():
    """The held-out accuracy figure drew bare depth maps (no colour bar) and events without an ON/OFF legend."""
    from benchmarks.accuracy import BAR_FONT_SCALE, MethodResult, SequenceSpec, depth_figure
    from cmax import viz
    from cmax.metrics import depth_metrics
    from conftest import random_events

    width, height = 60, 48
    gt = np.linspace(2.0, 8.0, width * height, dtype=np.float32).reshape(height, width)
    estimate = gt * 1.1
    estimate[:, :20] = np.nan                                   # "no estimate" on the left third
    metrics = depth_metrics(estimate, gt)
    results = [MethodResult("cmax.fit", "seq", metrics, estimate, gt, 1.0)]
    run = SimpleNamespace(spec=SequenceSpec("seq", "indoor_flying", 1), depth_range=(1.0, 10.0))
    picture = depth_figure(run, results, random_events(500, width=width, height=height, t_span_us=10_000, seed=2))
    bar = viz.depth_colour_bar(height, viz.DepthScale(float(np.percentile(gt, 1)), float(np.percentile(gt, 99))),
                               font_scale=BAR_FONT_SCALE)
    # the bar at the bottom right, level with the maps, on the 1st-99th percentiles of the ground truth
    assert np.array_equal(picture[-height:, -bar.shape[1]:], bar)
    pixels = picture[-height:].reshape(-1, 3)
    hatch = (pixels == viz.NO_DEPTH_BGR).all(axis=1) | (pixels == viz.NO_DEPTH_HATCH_BGR).all(axis=1)
    assert hatch.sum() >= 20 * height                           # every NaN pixel of the estimate is hatched
    title_rows = picture[:-height].reshape(-1, 3)
    assert (title_rows == viz.ON_BGR).all(axis=1).sum() >= 25   # the ON/OFF legend
    assert (title_rows == viz.OFF_BGR).all(axis=1).sum() >= 25


def test_se3_variants_pool_the_fit_seeds_and_compare_each_variant_fit_by_fit():
    from benchmarks.se3_variants import report

    def fits(directions):
        return [{"abs_rel": 0.1, "direction_deg": d, "omega_rms_deg_s": 1.0, "seconds": 1.0, "verdict": "ok"}
                for d in directions]

    rows = {"default": fits([1.0, 9.0, 3.0, 5.0]), "more": fits([2.0, 4.0, 3.0, 1.0])}   # windows 100, 101 x seeds 0, 1
    text = report(rows, [100, 101], 1.0, [0, 1])
    assert "fit seeds 0, 1 (4 fits per variant)" in text
    assert "| default | 0.100 / 0.100 | 4.000 / 7.800 |" in text        # pooled: median 4, p90 7.8
    assert "| more | 0 of 4 | 2 of 4 | 0 of 4 |" in text                 # lower than the default on 100/1 and 101/1
    assert "- more: 100/0 0.100 2.0 ok; 100/1 0.100 4.0 ok; 101/0 0.100 3.0 ok; 101/1 0.100 1.0 ok" in text


def test_se3_variants_parse_dotted_settings_and_refuse_unknown_fields():
    import pytest

    from benchmarks.se3_variants import parse_variant, settings_of
    from cmax.fitting import FitSettings

    variant = parse_variant("refine.iterations=150, patch_flow.max_events=10000,low_parallax_px=2.5")
    assert variant == {"refine.iterations": 150, "patch_flow.max_events": 10000, "low_parallax_px": 2.5}
    base = FitSettings(depth_range=(1.0, 6.5))
    s = settings_of(variant, base)
    assert (s.refine.iterations, s.patch_flow.max_events, s.low_parallax_px) == (150, 10000, 2.5)
    assert s.refine.max_events == base.refine.max_events and s.depth_range == (1.0, 6.5)
    deep = settings_of(parse_variant("patch_flow.tolerances.ftol=1e-6"), base)     # any depth
    assert deep.patch_flow.tolerances.ftol == 1e-6
    assert deep.patch_flow.tolerances.gtol == base.patch_flow.tolerances.gtol and deep.refine == base.refine
    for bad in ("refine.iteration=3", "refines.iterations=3", "refine.tolerances.xtol=1"):
        with pytest.raises(ValueError, match="no field"):
            settings_of(parse_variant(bad), base)
    with pytest.raises(ValueError, match="refine.iterations must be"):
        settings_of(parse_variant("refine.iterations=-1"), base)   # the dataclass's own validation
    with pytest.raises(ValueError, match="field=value"):
        parse_variant("refine.iterations")


def test_timed_machine_sets_the_clock_of_the_groups_and_records_it(monkeypatch):
    import benchmarks.speed as speed

    monkeypatch.setattr(speed, "CLOCK", ["wall"])
    machine = speed.timed_machine("cpu")
    assert speed.CLOCK == ["cpu"] and machine["clock"] == "cpu"
    assert set(speed.machine_info()) | {"clock"} == set(machine)


def test_accuracy_noise_worker_fits_the_exported_windows_as_accuracy_cmax_does(monkeypatch, tmp_path):
    """The worker process (this checkout's cmax, as --against-tree runs another's) gives, per window and fit
    seed, the figures accuracy_cmax computes in process for the same fit."""
    import benchmarks.accuracy_noise as noise
    from benchmarks.synthetic_windows import make_window

    from cmax.geometry import se3_exp

    made = make_window("slider", 7, width=120, height=90, focal=90.0, duration_s=0.1)
    duration_s = (made.events.t[-1] - made.events.t[0]) * 1e-6
    window = SimpleNamespace(events=made.events, K=made.K, twist=made.twist, depth=made.depth,
                             T01=se3_exp(made.twist * duration_s))    # a constant twist over the window
    monkeypatch.setattr(noise, "windows", lambda model, seed, cache: window)
    noise.export_windows(tmp_path, [100], None)
    rows = noise.by_model_and_seed(noise.run_workers(tmp_path, ["se3", "depth"], [0, 2], {"this": noise.ROOT})["this"],
                                   [0, 2])
    room = accuracy_cmax._room()
    for fit_seed in (0, 2):
        expected = accuracy_cmax.run_se3(window, seed=fit_seed, **room)
        (row,) = rows["se3"][fit_seed]
        assert row["window"] == 100
        for figure in ("abs_rel", "direction_deg", "omega_rms_deg_s"):
            assert row[figure] == pytest.approx(expected[figure], rel=1e-6, abs=1e-9), figure
        (row,) = rows["depth"][fit_seed]
        assert row["abs_rel"] == pytest.approx(accuracy_cmax.run_depth(window, seed=fit_seed, **room)["abs_rel"],
                                               rel=1e-6)


def test_accuracy_noise_places_the_reference_in_the_range_and_pairs_the_fits(tmp_path):
    import benchmarks.accuracy_noise as noise

    reference = tmp_path / "reference.md"
    reference.write_text("| model | figure | median | p90 | target | met |\n|---|---|---|---|---|---|\n"
                         "| se3 | abs_rel | 0.150 | 0.500 | <= 0.2 | yes / no |\n"
                         "| se3 (ok, 3 of 5) | abs_rel | 0.100 | 0.200 | <= 0.2 | yes / yes |\n")
    assert noise.reference_figures(reference.read_text()) == {("se3", "abs_rel"): (0.15, 0.5)}

    def results(values):
        return [{"window": 100 + i, "abs_rel": a, "direction_deg": 1.0, "omega_rms_deg_s": 1.0, "seconds": 1.0}
                for i, a in enumerate(values)]

    rows = {"se3": {0: results([0.1, 0.2, 0.3]), 1: results([0.2, 0.3, 0.4])}}
    text = noise.summarise(rows, [100, 101, 102], [0, 1], noise.reference_figures(reference.read_text()),
                           "ref", 1.0)
    # medians 0.2 and 0.3 (the reference's 0.15 is below them); p90s 0.28 and 0.38 (0.5 above)
    assert "| se3 | abs_rel | median | 0.200 | 0.300 | 0.200-0.300 | 0.150 | below the range |" in text
    assert "| se3 | abs_rel | p90 | 0.280 | 0.380 | 0.280-0.380 | 0.500 | above the range |" in text
    assert "- se3 abs_rel: 100: 0.1 0.2; 101: 0.2 0.3; 102: 0.3 0.4" in text

    before = {"se3": {0: results([0.2, 0.2, 0.2]), 1: results([0.1, 0.5, 0.2])}}
    table = "\n".join(noise.compare(before, rows, [0, 1], ("old", "new")))
    # new - old per fit: -0.1, 0, +0.1 (seed 0); +0.1, -0.2, +0.2 (seed 1)
    assert "- se3 abs_rel: new lower in 2 of 6 fits, higher in 3; median difference +0.05" in table
    # medians: old 0.2 and 0.2 (mean 0.2), new 0.2 and 0.3 (mean 0.25); pooled over the six fits: 0.2, 0.25
    assert "| se3 | abs_rel | median | 0.200 | 0.250 | 0.200 | 0.250 |" in table


def test_accuracy_noise_interval_resamples_whole_windows():
    """The pooled difference's 90% interval: a shift of every fit by c is exactly c in every resample (worse, or
    better for -c); one window far worse and the others equal give an interval from 0 (resamples without that
    window) upwards: within noise; the same windows and seeds give 0."""
    import benchmarks.accuracy_noise as noise

    rng = np.random.default_rng(1)
    before = rng.random((20, 5))
    for k in (0, 1):
        assert noise.pooled_difference_interval(before, before + 0.1, k) == pytest.approx((0.1, 0.1, 0.1))
        assert noise.pooled_difference_interval(before, before, k) == (0.0, 0.0, 0.0)
    assert noise._verdict(0.1, 0.1) == "worse" and noise._verdict(-0.2, -0.1) == "better"
    after = before.copy()
    after[3] += 5.0                                                      # one window of 20 far worse
    difference, low, high = noise.pooled_difference_interval(before, after, 1)
    assert difference > 0 and low == pytest.approx(0.0, abs=1e-12) and high > 0
    assert noise._verdict(low, high) == "within noise"


def test_speed_shared_objective_times_both_paths_and_finds_them_equal():
    """The shared-objective speed benchmark's calls, on two small windows: every call runs on both paths,
    each path is timed, and the compiled and torch values agree (float64 rows to float rounding)."""
    import torch

    from benchmarks.speed_patch_contrast import time_interleaved
    from benchmarks.speed_shared_objective import agreement, cases, compiled
    from benchmarks.synthetic_windows import make_window

    torch.set_num_threads(1)
    windows = [make_window("indoor_flying", seed, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=20)
               for seed in (3, 4)]
    speeds = [float(np.linalg.norm(w.twist[:3])) for w in windows]
    calls = cases(windows, speeds)
    assert len(calls) == 2 * 2 + 2                      # polish depth / depth_motion per window, loss, step
    times = time_interleaved(calls, 1, compiled)
    assert all(len(t["compiled"]) == len(t["torch"]) == 1 for t in times.values())
    for name, (value, gradient) in agreement(calls).items():
        if name.startswith("polish"):
            assert value < 1e-12 and gradient < 1e-10
        elif name.startswith("training loss"):
            assert value < 1e-5 and gradient < 0.05


def test_speed_fit_ab_reports_both_checkouts_and_refuses_a_folder_that_is_not_one(tmp_path):
    import pytest

    from benchmarks import speed_fit_ab

    root = Path(speed_fit_ab.__file__).resolve().parents[1]
    seconds = {"before": [2.0, 3.0, 1.0], "after": [1.0, 1.0, 1.0]}
    text = speed_fit_ab.report({"before": root, "after": root}, seconds, [100, 101, 102], (0.5, 0.7), "cmd")
    assert "| before |" in text and "| after |" in text and "`cmd`" in text
    assert "median 2.00, range 1.00-3.00" in text                       # per-window ratios 2, 3, 1
    assert "100: 2.00, 1.00; 101: 3.00, 1.00; 102: 1.00, 1.00" in text and "CPU seconds" not in text
    cpu = {"before": [1.0, 4.0, 1.5], "after": [1.0, 2.0, 1.0]}                 # CPU ratios 1, 2, 1.5
    text = speed_fit_ab.report({"before": root, "after": root}, seconds, [100, 101, 102], (0.5, 0.7), "cmd",
                               "depth", cpu)
    assert "# `cmax.fit` depth seconds" in text and "`pose=` the true motion" in text
    assert "median 1.500 before, 1.000 after; per-window ratio before / after: median 1.50, range 1.00-2.00" in text
    with pytest.raises(SystemExit):
        speed_fit_ab.main(["--before", str(tmp_path), "--output", str(tmp_path / "out.md")])
    assert not (tmp_path / "out.md").exists()


def test_real_cmax_seed_spread_counts_each_target_per_fit_seed():
    """Two fit seeds of a 4-window slider sequence: seed 0 meets every target, seed 1 has a reversed window,
    a p90 over 20 deg and its far wall at 60% of EMVS's; the table and the counts say so."""
    from benchmarks.real_cmax import FarWall, _seed_spread_lines
    from cmax.fitting import Verdict

    def sequence(directions_deg, unsteady=()):
        results = tuple(SimpleNamespace(v=np.array([np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0]),
                                        verdict=Verdict.OK, quality=SimpleNamespace(unsteady=i in unsteady))
                        for i, a in enumerate(directions_deg))
        return SimpleNamespace(results=results)

    good = [FarWall(2.0, 2.0 * r, 50, 1.5) for r in (0.94, 1.0, 1.04, 0.98)]
    bad = [FarWall(2.0, 2.0 * r, 50, 1.5) for r in (0.6, 0.6, 0.62, 1.0)]
    lines = _seed_spread_lines({0: (sequence([2, 4, 6, 8]), good, bad), 1: (sequence([5, 6, 30, 170]), bad, bad)})
    text = "\n".join(lines)
    assert "| 0 | 0 | 5.0 / 7.4 | 0.990 (0.97 / 1.01) | 0 | 0.610 | 4 ok |" in text
    assert "| 1 | 1 |" in text and "| 0.610 (0.60 / 0.71) | 3 | 0.610 |" in text
    assert "Targets met at 1 of 2 fit seeds (no reversed window), 1 of 2 (direction" in text
    assert "1 of 2 (far wall within 10% of EMVS; against EMVS over every event, blind to occlusion: 0 of 2)" in text
    assert "steady windows alone" not in text                                      # no unsteady window
    lines = _seed_spread_lines({0: (sequence([2, 4, 6, 8], unsteady=(3,)), bad, bad)})
    assert "seed 0: 0.600 without window(s) 3." in "\n".join(lines)               # median of 0.6, 0.6, 0.62


def test_window_cache_is_keyed_by_the_simulator_sources(tmp_path, monkeypatch):
    """A window cached by other simulator code is simulated again, not read back (``accuracy_cmax.cached``)."""
    from benchmarks import accuracy_cmax

    made = []

    def make():
        made.append(1)
        return {"window": len(made)}

    first = accuracy_cmax.cached(tmp_path, "w", make)
    assert accuracy_cmax.cached(tmp_path, "w", make) == first and len(made) == 1      # read back
    fingerprint = accuracy_cmax.simulation_fingerprint()
    assert len(fingerprint) == 12 and int(fingerprint, 16) >= 0
    assert (tmp_path / f"w_{fingerprint}.pkl").exists()
    monkeypatch.setattr(accuracy_cmax, "simulation_fingerprint", lambda: "0" * 12)
    assert accuracy_cmax.cached(tmp_path, "w", make) == {"window": 2} and len(made) == 2   # simulated again


def test_device_check_runs_every_part_and_fails_a_difference_beyond_its_tolerance(tmp_path, monkeypatch, capsys):
    """``benchmarks.device_check --device cpu`` (the CPU against itself: every difference 0) writes its table and
    exits 0; with a tolerance below 0 every comparison fails and it exits 1; a GPU where torch sees none is
    refused by the parser. ``relative`` is max |a - b| / max |b|."""
    from benchmarks import device_check

    assert device_check.relative(np.array([1.0, 2.0]), np.array([1.0, 4.0])) == pytest.approx(0.5)
    assert device_check.main(["--device", "cpu", "--out", str(tmp_path / "a.md")]) == 0
    text = (tmp_path / "a.md").read_text()
    assert text.count("| ok |") == 8 and "0 of 8 comparisons" in text
    monkeypatch.setattr(device_check, "TOLERANCE", {part: -1.0 for part in device_check.TOLERANCE})
    assert device_check.main(["--device", "cpu", "--out", str(tmp_path / "b.md")]) == 1
    assert "8 of 8 comparisons outside" in (tmp_path / "b.md").read_text()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit):
        device_check.main(["--device", "cuda", "--out", str(tmp_path / "c.md")])
    assert "sees no CUDA device" in capsys.readouterr().err


def test_solver_agreement_fits_each_solver_and_measures_the_gap_to_scipy(monkeypatch):
    """Each solver fits the same window; the gap is against L-BFGS-B's refinement objective, a failed stage is
    counted and named."""
    import benchmarks.solver_agreement as agreement
    from benchmarks.synthetic_windows import make_window

    small = make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    monkeypatch.setattr(agreement, "cached", lambda cache, key, make: small)
    rows = agreement.run(100, None)
    assert set(rows) == set(agreement.SOLVERS) and rows["scipy"]["gap_pct"] == 0.0
    for solver in agreement.SOLVERS:
        expected = 100 * (rows[solver]["refine"] - rows["scipy"]["refine"]) / abs(rows["scipy"]["refine"])
        assert rows[solver]["gap_pct"] == pytest.approx(expected) and abs(expected) < 2.0
        assert rows[solver]["success"] == (rows[solver]["failed"] == [])
    failed = {s: dict(r) for s, r in rows.items()}
    failed["casadi"].update(success=False, failed=["local_refine"], gap_pct=-3.0)
    text = agreement.report({100: rows, 101: failed}, 1.0, 0.0)
    casadi = next(line for line in text.splitlines() if line.startswith("| casadi |"))
    assert "| -3.00 |" in casadi and "1 of 2" in casadi and "no (local_refine)" in text


def test_rate_change_summary_row_counts_windows_over_the_threshold():
    from benchmarks.rate_change import summary_row

    row = summary_row("set", [1.0, 1.2, 1.4, 9.0], 6.0)
    # median of 1.0, 1.2, 1.4, 9.0 is 1.3; numpy's p99 interpolates 1.4 + 0.97 * 7.6 = 8.772
    assert row == "| set | 4 | 1.30 | 8.77 | 9.00 | 1 |"


def test_quality_sparse_table_counts_the_ok_and_the_bad_ok_verdicts_of_each_rule():
    from benchmarks.quality_sparse import table
    from cmax.fitting import Verdict

    def row(count, error, off, on):
        return {"count": count, "density": count / 89_960, "error_deg": error, "off": off, "on": on,
                "sparse": off is Verdict.OK and on is not Verdict.OK, "same_motion": True}

    rows = [row(3000, 50.0, Verdict.OK, Verdict.AMBIGUOUS), row(3000, 10.0, Verdict.OK, Verdict.AMBIGUOUS),
            row(3000, 70.0, Verdict.AMBIGUOUS, Verdict.AMBIGUOUS), row(40000, 5.0, Verdict.OK, Verdict.OK)]
    lines = table(rows)
    assert lines[2] == ("| 3,000 | 0.033 | 3 | 50.0 | 2 (1 bad: 50, 10 deg) | 0 (0 bad) | 2 | 3 of 3 |")
    assert lines[3] == ("| 40,000 | 0.445 | 1 | 5.0 | 1 (0 bad: 5 deg) | 1 (0 bad: 5 deg) | 0 | 1 of 1 |")


def test_background_noise_adds_the_rate_asked_and_reports_both_settings_of_each_window():
    """The added noise's count is Poisson with mean rate x pixels x span (closed form, within 4 sigma), its pixels
    and times lie in the image and the window, the scene's events are all kept; the report's medians and counts
    are those of the rows (off -> filter)."""
    from argparse import Namespace

    from benchmarks.background_noise import summarise, with_noise
    from cmax import Events

    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, 100_000, 5_000))
    scene = Events(rng.integers(0, 64, 5_000), rng.integers(0, 48, 5_000), t, rng.integers(0, 2, 5_000), 64, 48)
    noisy, added = with_noise(scene, 2.0, 7)
    expected = 2.0 * 64 * 48 * (int(t[-1]) - int(t[0])) * 1e-6
    assert abs(added - expected) < 4 * np.sqrt(expected)
    assert len(noisy) == len(scene) + added and np.all(np.diff(noisy.t) >= 0)
    assert noisy.t[0] == t[0] and noisy.t[-1] == t[-1]
    assert with_noise(scene, 0.0, 7)[1] == 0
    rows = [dict(preset="slider", seed=s, rate=1.0, setting=setting, abs_rel=a, direction=d, ok_wrong=w,
                 estimated=0.1, filtered=setting == "filter", added=0.2)
            for s, setting, a, d, w in [(1, "off", 0.3, 40.0, True), (1, "filter", 0.1, 5.0, False),
                                        (2, "off", 0.5, 10.0, False), (2, "filter", 0.2, 6.0, False)]]
    text = summarise(rows, Namespace(seeds="1-2", presets="slider", rates="1", size="64x48"), 1.0)
    assert "| slider | 1 | 0.400 -> 0.150 | 25.0 -> 5.5 | 1 -> 0 | 0.20 / 0.10 | 2 of 2 |" in text
    assert "made worse by more than 0.02: 0 of 2." in text
