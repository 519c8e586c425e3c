"""The glue between benchmark scripts: the speed section reuses the accuracy benchmark's runs (the fits
themselves are timed by the scripts, not here)."""
from __future__ import annotations

import benchmarks.accuracy_cmax as accuracy_cmax
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

