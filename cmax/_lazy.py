"""Public names of a package loaded on first access (PEP 562), so that importing it stays cheap.

Used by the packages whose modules import torch (``cmax``, ``cmax.fitting``,
``cmax.sim``): ``cmax info`` and the command line's parser then start without
loading torch (about 1.2 s on the reference machine).
"""
from __future__ import annotations

from importlib import import_module
from typing import Callable, Iterable

__all__ = ["lazy_exports"]


def lazy_exports(package: str, names: dict[str, str], namespace: dict, submodules: Iterable[str] = ()
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` of ``package`` for ``names`` (public name -> module).

    ``submodules`` are the package's modules reachable as attributes after a plain
    ``import package`` (``import cmax; cmax.io.read(...)``), imported on first access.
    Every value is cached in the package's ``namespace`` (its ``globals()``) on first access.
    """
    submodules = frozenset(submodules)

    def __getattr__(name: str) -> object:
        if name in names:
            value = getattr(import_module(names[name]), name)
        elif name in submodules:
            value = import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(names) | submodules)

    return __getattr__, __dir__
