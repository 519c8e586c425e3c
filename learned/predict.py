"""``python -m learned.predict --checkpoint CKPT FILE -o out/``: depth and twist of every window of an event file.

Writes per window ``window_<k>.npz`` (``depth`` (H, W) float32 [m], ``inverse_depth``,
``twist`` (6,) [m/s, rad/s], ``t0_us``, ``t1_us``) and ``window_<k>.png`` (a depth picture),
and ``twists.csv`` (one line per window). Every file is written atomically.
Files without ``gt/K`` need ``--K fx,fy,cx,cy``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from cmax._args import ArgumentParser, positive_float, run_main
from cmax.fitting.cli import intrinsics_argument
from cmax.io.atomic import save_npz_atomic, write_text_atomic
from learned.data import H5WindowDataset
from learned.evaluate import load_model, predict_batches

__all__ = ["predict_file", "main"]


def predict_file(checkpoint: str | Path, path: str | Path, out: str | Path, *, K: np.ndarray | None = None,
                 window_us: int | None = None, progress: bool = True) -> int:
    """Predict every window of ``path`` into folder ``out``; returns the number of windows."""
    from cmax import viz

    model, config = load_model(checkpoint)
    window_us = int(config["data"]["window_us"]) if window_us is None else int(window_us)
    if window_us < 1:
        raise ValueError(f"the window must be at least 1 µs long, got {window_us} µs")
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such event file: {path}")
    spec = {"path": str(path), "use_gt": False, **({"K": np.asarray(K, float).tolist()} if K is not None else {})}
    try:
        dataset = H5WindowDataset([spec], window_us=window_us, max_events=1000, bins=model.config.bins, min_events=10)
    except ValueError:
        if K is not None:
            raise
        dataset = H5WindowDataset([{"path": str(path)}], window_us=window_us, max_events=1000,
                                  bins=model.config.bins, min_events=10)
    if len(dataset) == 0:
        raise ValueError(f"{path}: no window of {window_us} µs with at least 10 events")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lines = ["window,t0_us,t1_us,vx,vy,vz,wx,wy,wz"]
    k = 0
    for batch, output in tqdm(predict_batches(model, dataset), total=-(-len(dataset) // 8), disable=not progress):
        for b in range(output.twist.shape[0]):
            _, t0 = dataset.index[k]
            inverse = output.inverse_depth[b, 0].numpy()
            twist = output.twist[b].numpy()
            save_npz_atomic(out / f"window_{k:05d}.npz", depth=(1.0 / inverse).astype(np.float32),
                        inverse_depth=inverse, twist=twist, t0_us=t0, t1_us=t0 + window_us)
            viz.save_png(out / f"window_{k:05d}.png",
                         viz.depth_panel((1.0 / inverse).astype(np.float32), None, "predicted depth"))
            lines.append(",".join([str(k), str(t0), str(t0 + window_us)] + [f"{v:.6g}" for v in twist]))
            k += 1
    write_text_atomic(out / "twists.csv", "\n".join(lines) + "\n")
    return k


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (2 and one line for a bad argument or file)."""
    parser = ArgumentParser(prog="python -m learned.predict", description=__doc__.splitlines()[0])
    parser.add_argument("file", type=Path, help="DSEC-layout h5 event file")
    parser.add_argument("--checkpoint", type=Path, required=True, help="checkpoint of learned.train (last.pt)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    parser.add_argument("--K", type=intrinsics_argument, default=None,
                        help="fx,fy,cx,cy for files without gt/K (default: the file's gt/K)")
    parser.add_argument("--window", type=positive_float, default=None,
                        help="window length [s] (default: the checkpoint config's data.window_us)")
    return run_main(parser, _run, argv)


def _run(args: argparse.Namespace) -> int:
    with torch.no_grad():
        n = predict_file(args.checkpoint, args.file, args.output, K=args.K,
                         window_us=None if args.window is None else int(round(args.window * 1e6)))
    print(f"{args.output}: {n} windows")
    return 0


if __name__ == "__main__":
    sys.exit(main())
