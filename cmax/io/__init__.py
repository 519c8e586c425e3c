"""Event file formats."""
from cmax.io.errors import FormatError

__all__ = ["FormatError"]
