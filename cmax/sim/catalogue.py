"""Catalogues of public videos (the SlowTV list behind EvtSlowTV) and shards of job lists.

The SlowTV catalogue (Spencer et al., "Kick back & relax: Learning to reconstruct
the world by watching SlowTV", ICCV 2023) lists 40 public videos by index, URL
and category, in the order their authors number them; they download them as
720p MP4 (YouTube format 136) named ``00000.mp4``, ``00001.mp4``, ... The list
is shipped as package data (``cmax/sim/data/slowtv_catalogue.tsv``, from
jspenmar/slowtv_monodepth ``api/data/splits/slow_tv/splits/{urls,categories}.txt``);
the videos are not.

>>> entries = load_catalogue("slowtv")
>>> len(entries), entries[0].index, entries[0].name
(40, 0, '00000')
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from typing import Sequence, TypeVar

__all__ = ["CATALOGUES", "CatalogueEntry", "load_catalogue", "parse_catalogue", "parse_shard", "shard"]

#: Catalogues shipped with the package: name -> file in ``cmax/sim/data``.
CATALOGUES = {"slowtv": "slowtv_catalogue.tsv"}

T = TypeVar("T")


@dataclass(frozen=True)
class CatalogueEntry:
    """One video of a catalogue: ``index`` (0-based), ``url`` and ``category``."""

    index: int
    url: str
    category: str

    @property
    def name(self) -> str:
        """File stem of the video and of its event file: the index on five digits."""
        return f"{self.index:05d}"


def parse_catalogue(text: str, *, source: str = "catalogue") -> list[CatalogueEntry]:
    """Entries of a tab-separated catalogue with the header ``index  url  category``.

    Raises
    ------
    ValueError
        A missing header, a line without three fields, a non-integer or repeated index.
    """
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if not lines or lines[0].split("\t")[:3] != ["index", "url", "category"]:
        raise ValueError(f"{source}: expected a header line 'index<TAB>url<TAB>category'")
    entries, seen = [], set()
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split("\t")
        if len(fields) != 3:
            raise ValueError(f"{source} line {number}: expected 3 tab-separated fields, got {line!r}")
        try:
            index = int(fields[0])
        except ValueError:
            raise ValueError(f"{source} line {number}: index must be an integer, got {fields[0]!r}") from None
        if index < 0 or index in seen:
            raise ValueError(f"{source} line {number}: index {index} is negative or repeated")
        seen.add(index)
        entries.append(CatalogueEntry(index, fields[1].strip(), fields[2].strip()))
    return entries


def load_catalogue(name: str = "slowtv") -> list[CatalogueEntry]:
    """A catalogue shipped with the package (``name`` in :data:`CATALOGUES`)."""
    if name not in CATALOGUES:
        raise ValueError(f"unknown catalogue {name!r}; known: {', '.join(sorted(CATALOGUES))}")
    text = resources.files("cmax.sim").joinpath("data", CATALOGUES[name]).read_text("utf-8")
    return parse_catalogue(text, source=f"catalogue {name!r}")


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> ``(i, n)`` with ``0 <= i < n`` (shard i of n, 0-based)."""
    try:
        i, n = (int(part) for part in str(text).split("/"))
    except ValueError:
        raise ValueError(f"shard must be 'i/n' such as 0/4, got {text!r}") from None
    if n < 1 or not 0 <= i < n:
        raise ValueError(f"shard i/n needs n >= 1 and 0 <= i < n, got {text!r}")
    return i, n


def shard(items: Sequence[T], i: int, n: int) -> list[T]:
    """Items ``i, i + n, i + 2n, ...``: the n shards are disjoint and cover ``items``.

    >>> shard(list(range(7)), 1, 3)
    [1, 4]
    """
    if n < 1 or not 0 <= i < n:
        raise ValueError(f"shard needs n >= 1 and 0 <= i < n, got i={i}, n={n}")
    return list(items[i::n])
