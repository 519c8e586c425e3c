"""evtslowtv's core: events, file formats, representations, simulation and contrast maximization.

``cmax.fit(events, K, model="se3", speed=1.0)`` fits one window (a worked example:
:func:`cmax.fitting.api.fit`), ``cmax.fit_sequence(events, K, window_us=100_000)`` a whole recording.
The solvers (``fit``, ``fit_sequence``, ``EMVS``) import torch; they load on first use so that
``import cmax`` and the file tools stay fast:

>>> import cmax
>>> cmax.fit.__module__    # loaded here, at its first use
'cmax.fitting.api'
"""
from cmax._lazy import lazy_exports
from cmax.camera import Camera
from cmax.events import STRUCTURED_DTYPE, Events, EventTensors, concatenate

__version__ = "0.1.0"

#: Public names loaded on first access: name -> module.
_LAZY = {
    "fit": "cmax.fitting", "fit_sequence": "cmax.fitting", "FitResult": "cmax.fitting",
    "FitSettings": "cmax.fitting", "SequenceResult": "cmax.fitting", "LowParallaxWarning": "cmax.fitting",
    "LowMotionWarning": "cmax.fitting", "BoundWarning": "cmax.fitting",
    "EMVS": "cmax.emvs", "SemiDenseDepth": "cmax.emvs",
    "fit_windows": "cmax.fitting",
}

#: Sub-packages and modules reachable after a plain ``import cmax`` (``cmax.io.read(...)``), loaded on first use.
_SUBMODULES = (
    "io", "sim", "representations", "fitting", "emvs", "metrics", "viz", "geometry", "warp", "iwe",
    "objectives", "contrast", "loss", "show", "demo",
)

__all__ = ["Camera", "Events", "EventTensors", "STRUCTURED_DTYPE", "concatenate", "__version__", *_LAZY]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals(), _SUBMODULES)
