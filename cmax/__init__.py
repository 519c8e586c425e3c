"""evtslowtv's core: events, file formats, representations, simulation and contrast maximization."""
from cmax.events import STRUCTURED_DTYPE, Events, EventTensors, concatenate

__version__ = "0.1.0"

__all__ = ["Events", "EventTensors", "STRUCTURED_DTYPE", "concatenate", "__version__"]
