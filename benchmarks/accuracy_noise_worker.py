"""Worker of :mod:`benchmarks.accuracy_noise`: fits exported windows with whichever ``cmax`` is importable.

Run as a script (``python benchmarks/accuracy_noise_worker.py FOLDER SEEDS MODELS``), not as a module, so
that ``PYTHONPATH`` chooses the ``cmax`` it measures (this checkout, or another version's checkout for a
before/after comparison); it imports nothing of ``benchmarks``. ``FOLDER`` holds one ``window_<window>.npz``
per held-out window (``x, y, t, p, width, height, K, twist, T01, depth, depth_range``); ``SEEDS`` is a comma
list of ``FitSettings.seed`` values, ``MODELS`` a comma list of ``se3``, ``depth``. Prints one JSON line per fit:
``model, window, fit_seed``, the figures of :mod:`benchmarks.accuracy_cmax` (``abs_rel`` on the fit's mask
with finite ground truth inside the depth range; se3: ``direction_deg``, ``omega_rms_deg_s``) and ``seconds``.
"""
from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch


def abs_rel(depth: np.ndarray, mask: np.ndarray, truth: np.ndarray, depth_range: np.ndarray) -> float:
    """``mean(|d - g| / g)`` over ``mask`` (H, W) where the truth ``g`` [m] is finite and inside
    ``depth_range`` (as ``benchmarks.accuracy_cmax.abs_rel``); NaN when no pixel is valid."""
    with np.errstate(invalid="ignore"):
        valid = mask & np.isfinite(truth) & (truth >= depth_range[0]) & (truth <= depth_range[1])
    if not valid.any():
        return float("nan")
    return float(np.mean(np.abs(depth[valid] - truth[valid]) / truth[valid]))


def fit_one(window: dict, index: int, model: str, fit_seed: int) -> dict:
    """Fit the held-out ``window`` (the arrays of its file) numbered ``index`` as ``model`` with
    ``seed=fit_seed``: its figures (see the module docstring)."""
    from cmax.events import Events
    from cmax.fitting import fit

    z = window
    events = Events(z["x"], z["y"], z["t"], z["p"], int(z["width"]), int(z["height"]))
    depth_range = tuple(float(d) for d in z["depth_range"])
    v, omega = z["twist"][:3], z["twist"][3:]
    start = time.perf_counter()
    if model == "depth":
        r = fit(events, z["K"], pose=z["T01"], depth_range=depth_range, seed=fit_seed)
    else:
        r = fit(events, z["K"], speed=float(np.linalg.norm(v)), depth_range=depth_range, seed=fit_seed)
    row = {"model": model, "window": index, "fit_seed": fit_seed,
           "abs_rel": abs_rel(r.depth, r.mask, z["depth"], z["depth_range"])}
    if model == "se3":
        cos = float(r.v @ v / (np.linalg.norm(r.v) * np.linalg.norm(v)))
        row["direction_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        row["omega_rms_deg_s"] = float(np.degrees(np.sqrt(np.mean((r.omega - omega) ** 2))))
    row["seconds"] = time.perf_counter() - start
    return row


def load_window(path: Path) -> tuple[int, dict]:
    """The window number and arrays of an exported ``window_<number>.npz``."""
    with np.load(path) as saved:
        return int(path.stem.rsplit("_", 1)[1]), {key: saved[key] for key in saved.files}


def main(argv: list[str]) -> int:
    folder, seeds, models = Path(argv[0]), [int(s) for s in argv[1].split(",")], argv[2].split(",")
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")       # the fits' low-parallax warnings: the figures say it
    files = sorted(folder.glob("window_*.npz"))
    index, window = load_window(files[0])
    fit_one(window, index, models[0], seeds[0])   # warm-up (compilation, torch's first calls), not reported
    for path in files:
        index, window = load_window(path)
        for model in models:
            for fit_seed in seeds:
                print(json.dumps(fit_one(window, index, model, fit_seed)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
