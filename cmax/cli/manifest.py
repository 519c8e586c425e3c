"""The ``cmax manifest merge`` command: join the ``manifest.json`` files of several conversions (shards, machines)."""
from __future__ import annotations

import argparse
import os
import sys
from contextlib import nullcontext
from pathlib import Path
from typing import Sequence

__all__ = ["add_command", "run"]


def _duplicates(paths: Sequence[Path], manifests: Sequence[dict]) -> tuple[list[str], list[str]]:
    """Names listed by several manifests: (conflicts: two different ``ok`` entries; notes: the others)."""
    seen: dict[str, list[tuple[Path, dict]]] = {}
    for path, manifest in zip(paths, manifests):
        for name, entry in manifest["videos"].items():
            seen.setdefault(name, []).append((path, entry))
    conflicts, notes = [], []
    for name, entries in sorted(seen.items()):
        if len(entries) < 2:
            continue
        oks = [(path, entry) for path, entry in entries if entry.get("status") == "ok"]
        where = ", ".join(f"{entry.get('status')} in {path}" for path, entry in entries)
        if len({repr(sorted((k, v) for k, v in e.items() if k != "wall_s")) for _, e in oks}) > 1:
            conflicts.append(f"{name} ({where})")
        else:
            kept = oks[0][0] if oks else entries[-1][0]
            notes.append(f"{name}: {where}; kept the entry of {kept}")
    return conflicts, notes


def run(args: argparse.Namespace) -> int:
    """Merge the manifests and write the result; returns the exit status (0).

    The merge holds the lock a conversion takes on the folder of ``-o`` (``.conversion.lock``), from the
    check of ``-o`` to its rename: a merge into a folder being converted (or a conversion started during a
    merge) is refused at once, so neither replaces the other's manifest. An existing ``-o`` is refused
    (FileExistsError) unless ``--overwrite``.
    """
    from cmax.io.atomic import PathLock
    from cmax.sim.convert import FOLDER_LOCK

    folder = args.output.parent
    # a missing folder is being converted by no one; the merge then says what else is wrong, or that it is missing
    with PathLock(folder / FOLDER_LOCK, folder) if folder.is_dir() else nullcontext():
        if os.path.lexists(args.output) and not args.overwrite:
            raise FileExistsError(f"{args.output} exists: pass --overwrite to replace it (to keep its videos, "
                                  "list it among the manifests to merge)")
        return _merge(args)


def _merge(args: argparse.Namespace) -> int:
    """Merge and write, under the folder's lock (see :func:`run`)."""
    from cmax.sim.convert import load_manifest, merge_manifests, write_manifest

    manifests = [load_manifest(path) for path in args.manifests]  # each checked: one line naming the file
    conflicts, notes = _duplicates(args.manifests, manifests)
    if conflicts:
        raise ValueError(f"{len(conflicts)} videos were converted differently in several manifests: "
                         f"{'; '.join(conflicts[:5])}{' ...' if len(conflicts) > 5 else ''}; "
                         "merge only one conversion of each video")
    # outputs relative to the merged manifest's folder (shard0/00000.h5), where a resume looks for them
    merged = merge_manifests(manifests, folders=[path.parent for path in args.manifests], into=args.output.parent,
                             names=[str(path) for path in args.manifests])
    write_manifest(args.output, merged)
    totals = merged["totals"]
    for note in notes:
        print(f"  listed more than once: {note}", file=sys.stderr)
    print(f"wrote {args.output}: {totals['videos']} videos ({totals['failed']} failed), "
          f"{len(merged['missing'])} missing, {len(notes)} listed more than once")
    return 0


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``manifest`` (with its action ``merge``) to an ``argparse`` sub-parser collection; returns the new
    parser."""
    parser = subparsers.add_parser("manifest", help="join the manifests of several conversions",
                                   description="Join manifest.json files of several conversions.")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    merge = actions.add_parser(
        "merge", help="merge manifest.json files (shards, machines)",
        description="Merge manifest.json files (shards, machines). A video listed by several manifests keeps its "
        "ok entry and is reported; two different ok entries of one video are refused (exit 2). Outputs are "
        "listed relative to the folder of -o (shard0/00000.h5), which must hold the manifests' folders; a "
        "conversion resumed into that folder verifies and skips them. An existing -o is refused without "
        "--overwrite; a merge into a folder being converted is refused (its lock .conversion.lock is held).")
    merge.add_argument("manifests", nargs="+", type=Path, help="manifest.json files")
    merge.add_argument("-o", "--output", type=Path, required=True, help="merged manifest to write")
    merge.add_argument("--overwrite", action="store_true",
                       help="replace an existing -o (list it among the manifests to keep its videos)")
    merge.set_defaults(run=run)
    return parser
