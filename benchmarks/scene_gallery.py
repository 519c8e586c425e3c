"""Pictures of every preset scene: rendered frame, 30 ms of simulated events (ON/OFF legend), ground-truth
depth (colour bar in metres, on the map's own 1st-99th percentiles; "no estimate" hatched grey).

Run ``python -m benchmarks.scene_gallery``; writes ``benchmarks/results/scenes_gallery.png``
(one row per preset) and ``benchmarks/results/scenes/<preset>.png``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cmax.sim import EventSimulator, PRESETS, make_scene, simulate_scene
from cmax.viz import depth_panel, event_panel, hstack, save_image, titled, vstack
from cmax.representations import event_frame

RESULTS = Path(__file__).resolve().parent / "results"


def preset_row(name: str, *, seed: int, width: int, height: int, t_s: float, window_s: float) -> np.ndarray:
    """Rendered frame, events of ``[t_s - window_s, t_s)`` and depth at ``t_s`` of one preset."""
    scene = make_scene(name, seed=seed, width=width, height=height, duration_s=max(1.0, 2 * t_s))
    sequence = simulate_scene(
        scene, window_s, EventSimulator(**{**scene.recommended_simulator, "seed": seed}),
        t0_s=t_s - window_s, depth_times_s=np.array([t_s]),
    )
    intensity, _ = scene.render(t_s)
    grey = np.repeat(np.clip(intensity, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    info = scene.info
    depth_text = f"depth (preset {info.depth_range_m[0]:g}-{info.depth_range_m[1]:g} m)" if info else "depth"
    depth = sequence.depth[0]
    return hstack([
        titled(grey, f"{name} (seed {seed})"),
        event_panel(event_frame(sequence.events), f"{window_s * 1e3:g} ms, {len(sequence.events):,} events"),
        depth_panel(depth, None, depth_text),
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", default="346x260")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    (RESULTS / "scenes").mkdir(parents=True, exist_ok=True)
    rows = []
    for name in sorted(PRESETS):
        row = preset_row(name, seed=args.seed, width=width, height=height, t_s=0.5, window_s=0.03)
        save_image(RESULTS / "scenes" / f"{name}.png", row)
        rows.append(row)
        print(f"drew {name}")
    save_image(RESULTS / "scenes_gallery.png", vstack(rows))
    print(f"wrote {RESULTS / 'scenes_gallery.png'}")


if __name__ == "__main__":
    main()
