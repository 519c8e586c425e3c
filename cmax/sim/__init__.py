"""Simulation of event cameras: the ESIM event model, synthetic scenes with ground truth,
adaptive sampling and video sources.

>>> from cmax.sim import EventSimulator, make_scene, simulate_scene
>>> scene = make_scene("slider", width=32, height=24, duration_s=1.0, texture_size=64)
>>> sequence = simulate_scene(scene, 0.2, EventSimulator(seed=0), depth_rate_hz=10)
>>> sequence.events.sensor_size, len(sequence.depth_t_us) > 0, len(sequence.events) > 0
((32, 24), True, True)

The public names load on first use (the renderer imports torch), so that the
command line's parser, which lists :data:`PRESETS`, starts fast.
"""
from cmax._lazy import lazy_exports

_LAZY = {
    "EsimSettings": "cmax.sim.esim", "EventSimulator": "cmax.sim.esim",
    "PRESETS": "cmax.sim.presets", "make_scene": "cmax.sim.presets",
    "iter_upsample": "cmax.sim.sampling", "upsample": "cmax.sim.sampling",
    "PlanarScene": "cmax.sim.scenes", "RGBDScene": "cmax.sim.scenes", "TimeScaledScene": "cmax.sim.scenes", "SceneInfo": "cmax.sim.scenes",
    "SyntheticSequence": "cmax.sim.synthetic", "load_sequence": "cmax.sim.synthetic",
    "simulate_scene": "cmax.sim.synthetic", "open_source": "cmax.sim.video",
}

__all__ = sorted(_LAZY)

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
