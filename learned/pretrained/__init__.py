"""The depth-pose network that ships inside the package, and its model card.

``learned/pretrained/student.pt`` is a checkpoint of :mod:`learned.checkpoint` (loaded with
``weights_only=True`` like any other) and ``student.json`` beside it its card: the config and
scores of the run that produced it, and optionally the camera it was trained with
(``"size": [W, H]`` [px], ``"K": [fx, fy, cx, cy]`` [px]), which ``cmax depth`` compares
with the file it reads, and optionally ``"limits"``: what the model is known to get wrong, measured
(a list of sentences), which ``cmax depth`` prints as notes and records in its summary. Nothing here
imports torch.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["CHECKPOINT", "CARD", "shipped_checkpoint", "checkpoint_card", "card_limits"]

_HERE = Path(__file__).resolve().parent
#: Where the shipped checkpoint and its card live (package data).
CHECKPOINT, CARD = _HERE / "student.pt", _HERE / "student.json"

_HOW_TO_TRAIN = ("train one with 'python -m learned.train --mode student --config CONFIG' (docs/learned.md) "
                 "and pass it with --checkpoint RUN/last.pt")


def shipped_checkpoint() -> Path:
    """The path of the shipped checkpoint ``learned/pretrained/student.pt``.

    Raises
    ------
    FileNotFoundError
        One line saying how to train a model when this installation ships none.
    """
    if not CHECKPOINT.is_file():
        raise FileNotFoundError(f"no trained model ships with this installation ({CHECKPOINT} is absent): "
                                + _HOW_TO_TRAIN)
    return CHECKPOINT


def checkpoint_card(checkpoint: str | Path) -> dict[str, Any] | None:
    """The card of a checkpoint: the JSON file of the same stem beside it (``student.pt`` ->
    ``student.json``), as a dict; None when there is none.

    Raises ValueError naming the file when it is not a JSON object.
    """
    card = Path(checkpoint).with_suffix(".json")
    if not card.is_file():
        return None
    try:
        values = json.loads(card.read_text("utf-8"))
    except (ValueError, UnicodeDecodeError) as error:
        raise ValueError(f"{card} (the card of {checkpoint}) is not valid JSON: {error}") from None
    if not isinstance(values, dict):
        raise ValueError(f"{card} (the card of {checkpoint}) must hold a JSON object, got {type(values).__name__}")
    return values


def card_limits(card: dict[str, Any] | None, where: str = "the card") -> list[str]:
    """The card's ``"limits"``: sentences saying what the model is known to get wrong (empty when the card has
    none, or there is no card).

    >>> card_limits({"limits": ["its translation points the wrong way"]})
    ['its translation points the wrong way']
    >>> card_limits(None)
    []

    Raises ValueError naming ``where`` when ``"limits"`` is not a list of non-empty strings.
    """
    limits = (card or {}).get("limits", [])
    if not (isinstance(limits, list) and all(isinstance(text, str) and text.strip() for text in limits)):
        raise ValueError(f"{where}: 'limits' must be a list of sentences (non-empty strings), got {limits!r}")
    return list(limits)
