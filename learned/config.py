"""Training configuration: frozen dataclasses read from JSON or TOML, with ``key=value`` overrides.

A config file holds the sections ``model`` (:class:`learned.model.ModelConfig`),
``data`` and ``train``; the command line overrides single fields with dotted
keys (``train.steps=200 model.width=8``; values are parsed as JSON, else kept
as strings).
"""
from __future__ import annotations

import json
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from learned.model import ModelConfig

__all__ = ["DataConfig", "TrainConfig", "Config", "load_config", "apply_overrides", "MODES"]

MODES = ("teacher", "finetune", "student")


@dataclass(frozen=True)
class DataConfig:
    """Which windows to train on.

    Attributes
    ----------
    files : list
        Paths, or ``{"path", "K": [fx, fy, cx, cy], "use_gt": bool}`` (see :class:`learned.data.FileSpec`).
    window_us : int
        Window length [µs] (the paper's 0.1665 s).
    max_events : int
        Raw events per window kept for the contrast loss.
    augment : bool
    workers : int
        DataLoader worker processes (0: load in the training process).
    """

    files: tuple = ()
    window_us: int = 166_500
    max_events: int = 20_000
    augment: bool = True
    workers: int = 0


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and logging.

    Attributes
    ----------
    batch_size : int
        Global batch (split over the ranks of a ``torchrun`` job).
    lr, weight_decay : float
        AdamW (the paper: 1e-4, 1e-3).
    steps : int
        Optimiser steps in total.
    lam : float
        The paper's lambda (teacher: ``L_si + lam L_grad``; student: ``(1 - lam) L1``).
    teacher : str
        Checkpoint of the teacher (modes ``finetune``: initial weights; ``student``: the frozen teacher).
    out : str
        Run folder: checkpoints ``last.pt`` and ``step_<n>.pt``, TensorBoard logs.
    checkpoint_every, log_every, image_every : int
        In steps.
    seed : int
    collapse_weight : float
        Weight of the deformation guard added to the shared contrast objective (0: the objective alone,
        :data:`cmax.contrast.SHARED_OBJECTIVE`, which needs no guard).
    si_variance_weight : float
        w of ``L_si = mean(R^2) - w mean(R)^2`` (1: the paper's fully invariant form, which leaves the
        scale free; 0.85 keeps a weak pull towards metric scale, as in most supervised depth networks).
    twist_weight : float
        Teacher only: weight of a smooth-L1 loss between the predicted and the true twist (scaled by
        the model's bounds), so that the pose head starts from a sensible motion; 0 = the paper's teacher.
    """

    batch_size: int = 16
    lr: float = 1e-4
    weight_decay: float = 1e-3
    steps: int = 1000
    lam: float = 0.6
    teacher: str = ""
    out: str = "runs/learned"
    checkpoint_every: int = 100
    log_every: int = 10
    image_every: int = 100
    seed: int = 0
    collapse_weight: float = 0.0
    si_variance_weight: float = 0.85
    twist_weight: float = 1.0


@dataclass(frozen=True)
class Config:
    mode: str = "teacher"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.train.batch_size < 1 or self.train.steps < 0:
            raise ValueError(f"train.batch_size must be >= 1 and train.steps >= 0, got {self.train}")
        if self.mode in ("finetune", "student") and not self.train.teacher:
            raise ValueError(f"mode {self.mode!r} needs train.teacher (a teacher checkpoint)")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _section(cls, values: dict, name: str):
    known = {f.name for f in fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"unknown keys in [{name}]: {sorted(unknown)} (known: {sorted(known)})")
    values = {k: tuple(v) if isinstance(v, list) and k == "files" else v for k, v in values.items()}
    return cls(**values)


def config_from_dict(values: dict[str, Any]) -> Config:
    """A :class:`Config` from nested dicts (as written by :meth:`Config.to_dict`)."""
    unknown = set(values) - {"mode", "model", "data", "train"}
    if unknown:
        raise ValueError(f"unknown config sections: {sorted(unknown)}")
    return Config(mode=values.get("mode", "teacher"),
                  model=_section(ModelConfig, values.get("model", {}), "model"),
                  data=_section(DataConfig, values.get("data", {}), "data"),
                  train=_section(TrainConfig, values.get("train", {}), "train"))


def _parse(value: str) -> Any:
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value


def apply_overrides(values: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Set dotted keys (``train.steps=10``) in nested dicts; returns a new dict."""
    values = json.loads(json.dumps(values))
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"overrides must look like section.key=value, got {item!r}")
        *path, last = key.split(".")
        target = values
        for part in path:
            target = target.setdefault(part, {})
        target[last] = _parse(raw)
    return values


def load_config(path: str | Path | None, overrides: list[str] = (), *, mode: str | None = None) -> Config:
    """Read a ``.json`` or ``.toml`` config (or start from the defaults), apply overrides and ``mode``."""
    values: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if path.suffix == ".json":
            values = json.loads(path.read_text())
        elif path.suffix == ".toml":
            values = tomllib.loads(path.read_text())
        else:
            raise ValueError(f"config must be a .json or .toml file, got {path}")
    values = apply_overrides(values, list(overrides))
    if mode is not None:
        values["mode"] = mode
    return config_from_dict(values)


def with_mode(config: Config, mode: str) -> Config:
    return replace(config, mode=mode)
