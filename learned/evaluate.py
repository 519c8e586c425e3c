"""``python -m learned.evaluate --checkpoint CKPT --data FILE [FILE ...]``: depth and motion metrics of a network.

Each file with ground truth (``cmax scene`` / ``SyntheticSequence.save``) is cut into
windows centred on its ground-truth depth times (:class:`learned.data.H5WindowDataset`,
no augmentation); the network's full-resolution depth is scored against the true depth
with :func:`cmax.metrics.depth_metrics` (pooled over the file's windows, on every pixel
with valid ground truth up to the scene's far limit, capped at 80 m as in
``benchmarks/accuracy.py``; the prediction is dense, so ``coverage`` is 1), the twist
with :func:`cmax.metrics.motion_metrics`.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np
import torch

from cmax._args import ArgumentParser, positive_float, run_main
from cmax.metrics import DepthMetrics, MotionMetrics, depth_metrics, motion_metrics
from cmax.io.atomic import write_text_atomic
from learned.checkpoint import CheckpointError, load_checkpoint
from learned.config import config_from_dict
from learned.data import H5WindowDataset, collate
from learned.model import DepthPoseNet

__all__ = ["FileReport", "load_model", "predict_batches", "evaluate_files", "write_accuracy_csv", "main"]

CSV_COLUMNS = ("method", "sequence", "abs_mean_m", "rmse_log", "abs_rel", "err_10m", "err_20m", "err_30m",
               "coverage", "n_pixels")
FAR_LIMIT_M = 80.0


@dataclass(frozen=True, eq=False)
class FileReport:
    """Metrics of one file: its stem, the pooled depth metrics, the motion metrics (or None), windows."""

    sequence: str
    depth: DepthMetrics
    motion: MotionMetrics | None
    windows: int


def load_model(checkpoint: str | Path) -> tuple[DepthPoseNet, dict]:
    """The network of a checkpoint (eval mode) and its config dict (validated).

    Raises FileNotFoundError or :class:`learned.checkpoint.CheckpointError` (a ValueError) for a
    missing, foreign, crafted or inconsistent checkpoint (see :func:`learned.checkpoint.load_checkpoint`).
    """
    ckpt = load_checkpoint(checkpoint)
    try:
        config = config_from_dict(ckpt["config"])
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{checkpoint}: its config is not valid: {error}") from None
    model = DepthPoseNet(config.model)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as error:  # missing / unexpected keys, shapes that do not match the config
        raise CheckpointError(f"{checkpoint}: the weights do not match its model config "
                              f"({' '.join(str(error).split())[:300]})") from None
    return model.eval(), config.to_dict()


@torch.no_grad()
def predict_batches(model: DepthPoseNet, dataset: torch.utils.data.Dataset, batch_size: int = 8):
    """Yield (batch, output) over a dataset in order."""
    for start in range(0, len(dataset), batch_size):
        batch = collate([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        yield batch, model(batch["volume"])


def _far_limit(path: Path) -> float:
    with h5py.File(path, "r") as f:
        scene = f.attrs.get("scene")
    try:
        far = float(json.loads(scene)["depth_range_m"][1]) if scene is not None else FAR_LIMIT_M
    except (TypeError, ValueError, KeyError):
        far = FAR_LIMIT_M
    return min(far, FAR_LIMIT_M)


def evaluate_files(checkpoint: str | Path, files: Sequence[str | Path], *, window_s: float | None = None,
                   batch_size: int = 8) -> list[FileReport]:
    """Metrics of ``checkpoint`` on each file with ground truth (window length from the checkpoint's config)."""
    model, config = load_model(checkpoint)
    window_us = int(round(window_s * 1e6)) if window_s is not None else int(config["data"]["window_us"])
    if window_us < 1:
        raise ValueError(f"the window must be at least 1 µs long, got {window_s} s")
    reports = []
    for path in map(Path, files):
        dataset = H5WindowDataset([path], window_us=window_us, max_events=1000, bins=model.config.bins,
                                  min_events=10)
        if dataset._gt[0] is None:
            raise ValueError(f"{path} has no gt/: evaluation needs ground truth")
        if len(dataset) == 0:
            raise ValueError(f"{path}: no window of {window_us} µs with ground truth and at least 10 events")
        preds, gts, v, w, v_gt, w_gt = [], [], [], [], [], []
        for batch, out in predict_batches(model, dataset, batch_size):
            preds.append(out.depth[:, 0].numpy())
            mask = batch["depth_mask"][:, 0].numpy()
            gts.append(np.where(mask, 1.0 / np.where(mask, batch["inverse_depth"][:, 0].numpy(), 1.0), np.nan))
            keep = batch["has_twist"].numpy()
            v.append(out.twist[keep, :3].numpy()), w.append(out.twist[keep, 3:].numpy())
            v_gt.append(batch["twist"][keep, :3].numpy()), w_gt.append(batch["twist"][keep, 3:].numpy())
        metrics = depth_metrics(np.concatenate(preds), np.concatenate(gts), max_depth=_far_limit(path))
        motion = None
        if sum(len(a) for a in v):
            motion = motion_metrics(np.concatenate(v), np.concatenate(w), np.concatenate(v_gt), np.concatenate(w_gt))
        reports.append(FileReport(path.stem, metrics, motion, len(dataset)))
    return reports


def csv_row(method: str, report: FileReport) -> dict[str, object]:
    m = report.depth
    return {"method": method, "sequence": report.sequence, "abs_mean_m": m.abs_mean, "rmse_log": m.rmse_log,
            "abs_rel": m.abs_rel, "err_10m": m.cutoff_errors[10.0], "err_20m": m.cutoff_errors[20.0],
            "err_30m": m.cutoff_errors[30.0], "coverage": m.coverage, "n_pixels": m.n_pixels}


def write_accuracy_csv(path: str | Path, rows: Sequence[tuple[str, FileReport]]) -> Path:
    """The rows (method, report) as ``accuracy_learned.csv`` (columns of ``benchmarks/accuracy.py``), atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for method, report in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in csv_row(method, report).items()})
    return write_text_atomic(path, buffer.getvalue())


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (2 and one line for a bad argument or file)."""
    parser = ArgumentParser(prog="python -m learned.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True, help="checkpoint of learned.train (last.pt)")
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="h5 files with gt/")
    parser.add_argument("--window", type=positive_float, default=None,
                        help="window length [s] (default: the checkpoint config's data.window_us)")
    return run_main(parser, _run, argv)


def _run(args: argparse.Namespace) -> int:
    for report in evaluate_files(args.checkpoint, args.data, window_s=args.window):
        m = report.depth
        line = (f"{report.sequence}: {report.windows} windows  abs_mean {m.abs_mean:.3f} m  abs_rel {m.abs_rel:.3f}  "
                f"rmse_log {m.rmse_log:.3f}  delta1 {m.delta1:.3f}  "
                + "  ".join(f"<{c:g}m {e:.3f}" for c, e in m.cutoff_errors.items()))
        if report.motion is not None:
            line += (f"  omega_rms {report.motion.omega_rms_deg_s:.2f} deg/s  v_rms {report.motion.v_rms_m_s:.3f} m/s")
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
