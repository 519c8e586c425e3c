"""``cmax demo``: the end-to-end demo on data it makes itself.

Renders a synthetic ``indoor_flying`` scene (ground-truth depth and poses),
simulates its events with the ESIM model, writes them with the ground truth to
a DSEC-layout HDF5 file, and draws a report picture: the rendered frame, the
events of a 50 ms window, the ground-truth depth and the event-volume bins.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["run_demo"]


def run_demo(
    output_dir: str | os.PathLike = "demo_output", *, seed: int = 0, duration_s: float = 0.5,
    scene_name: str = "indoor_flying", window_s: float = 0.05,
) -> Path:
    """Run the demo, writing into ``output_dir``; returns the path of the report picture.

    Writes ``<scene>.h5`` (events + ``gt/``), ``summary.txt`` (what ``cmax info``
    prints) and ``report.png``.
    """
    from cmax.io.info import file_info
    from cmax.show import read_window, render_events
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene
    from cmax.viz import hstack, save_png, titled, vstack

    if not 2 * window_s <= duration_s:
        raise ValueError(f"duration_s must be at least twice window_s={window_s}, got {duration_s}")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    print(f"[1/3] rendering '{scene_name}' (seed {seed}) and simulating {duration_s} s of events ...")
    scene = make_scene(scene_name, seed=seed, duration_s=max(duration_s, 1.0))
    middle = duration_s / 2
    sequence = simulate_scene(
        scene, duration_s, EventSimulator(cp=0.2, cn=0.2, seed=seed),
        depth_times_s=np.array([middle]),
    )
    path = sequence.save(output_dir / f"{scene_name}.h5", overwrite=True)

    print(f"[2/3] wrote {path}")
    summary = "\n".join(file_info(path).lines())
    (output_dir / "summary.txt").write_text(summary + "\n")
    print(summary)

    print("[3/3] drawing the report ...")
    # The window is centred on the ground-truth depth map; times after the file's first event.
    t0_s = (int(sequence.depth_t_us[0]) - sequence.events.t_start) / 1e6 - window_s / 2
    events, depth = read_window(path, max(t0_s, 0.0), window_s)
    intensity, _ = scene.render(middle)
    frame = np.repeat(np.clip(intensity, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    picture = render_events(events, mode="both", depth=depth, title=f"{window_s * 1e3:g} ms: ")
    report = vstack([hstack([titled(frame, f"rendered frame, t={middle:g} s")]), picture])
    return save_png(output_dir / "report.png", report)
