"""The output folder of a run of :mod:`learned` (``cmax depth -o OUT``, ``train.out``), held by one run at a time:
:func:`cmax.io.run_folder.locked_folder`, which ``cmax fit -o`` uses too."""
from __future__ import annotations

from cmax.io.run_folder import locked_folder

__all__ = ["locked_folder"]
