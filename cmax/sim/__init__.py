"""Simulation of event cameras: the ESIM event model, synthetic scenes with ground truth,
adaptive sampling and video sources.

>>> from cmax.sim import EventSimulator, make_scene, simulate_scene  # doctest: +SKIP
"""
from cmax.sim.esim import EsimSettings, EventSimulator
from cmax.sim.presets import PRESETS, make_scene
from cmax.sim.sampling import iter_upsample, upsample
from cmax.sim.scenes import PlanarScene, RGBDScene, SceneInfo
from cmax.sim.synthetic import SyntheticSequence, load_sequence, simulate_scene
from cmax.sim.video import open_source

__all__ = [
    "EsimSettings", "EventSimulator", "PRESETS", "make_scene", "PlanarScene", "RGBDScene",
    "SceneInfo", "SyntheticSequence", "iter_upsample", "load_sequence", "open_source",
    "simulate_scene", "upsample",
]
