"""``steelscan train-detector`` and ``calibrate-detector``: the crack network made and
calibrated from dataset folders (PyTorch and onnx from the ``[train]`` extra)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from server.errors import CommandError


def _roots(folders: list[str]) -> list[Path]:
    roots = [Path(d) for d in folders]
    for r in roots:
        if not (r / "images").is_dir() or not (r / "masks").is_dir():
            raise CommandError(f"{r}: not a dataset folder (needs images/ and masks/)")
    return roots


def _steel(n: int, seed: int) -> dict[str, Any]:
    """The simulator's rendered steel as one more set (none when ``n`` is 0)."""
    if not n:
        return {}
    from processing.learning.data import Sample
    from robot_link.sim.steel_crops import steel_samples

    return {"steel-synthetic": [Sample(*s) for s in steel_samples(n, seed=seed)]}


def cmd_train_detector(args: argparse.Namespace) -> int:
    """Train the crack network on dataset folders and export it to ONNX (int8)."""
    try:
        from processing.learning.network import NetworkParams
        from processing.learning.train import TrainParams, leave_one_out, train_from_folders
    except ImportError as exc:
        raise CommandError(
            f"training needs PyTorch and onnx ({exc.name} is missing): "
            "pip install 'steelscan[train]'"
        ) from None
    roots = _roots(args.datasets)
    params = TrainParams(
        iterations=args.iterations,
        batch=args.batch,
        seed=args.seed,
        threads=args.threads,
        centre_weight=args.centre_weight,
        network=NetworkParams(tuple(args.channels)) if args.channels else NetworkParams(),
    )
    if args.budget_minutes is not None and not args.checkpoint:
        raise CommandError("--budget-minutes needs --checkpoint (to resume where it stops)")
    if args.leave_one_out and (args.synthetic_steel or args.checkpoint):
        raise CommandError("--leave-one-out trains on the folders only, in one sitting")
    extra = _steel(args.synthetic_steel, args.seed)
    try:
        if args.leave_one_out:
            records = leave_one_out(roots, Path(args.out), params, args.limit, not args.float)
            print(json.dumps({k: v["threshold"] for k, v in records.items()}))
            return 0
        record = train_from_folders(
            roots,
            Path(args.out),
            params,
            args.limit,
            not args.float,
            extra=extra,
            checkpoint=Path(args.checkpoint) if args.checkpoint else None,
            budget_s=args.budget_minutes * 60 if args.budget_minutes is not None else None,
        )
    except ValueError as exc:  # a checkpoint of another run, a set without images
        raise CommandError(str(exc)) from None
    keys = ("threshold", "parameters", "iterations_done", "complete", "train_seconds")
    print(json.dumps({k: record[k] for k in keys}))
    return 0


def cmd_calibrate_detector(args: argparse.Namespace) -> int:
    """Fit a crack model's per-defect confidence on the held-back images of its sets."""
    try:
        from processing.learning.calibration import calibrate_exported
        from processing.learning.data import load_dataset
    except ImportError as exc:
        raise CommandError(
            f"calibration needs onnx ({exc.name} is missing): pip install 'steelscan[train]'"
        ) from None
    model_path = Path(args.model)
    if not model_path.is_file():
        raise CommandError(f"{model_path}: no such model file")
    sets = {r.name: load_dataset(r, args.limit) for r in _roots(args.datasets)}
    sets |= _steel(args.synthetic_steel, args.seed)
    try:
        record = calibrate_exported(model_path, sets, threads=args.threads, strict=True)
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    print(json.dumps(record))
    return 0


def add_train_commands(sub: Any) -> None:
    """Add ``train-detector`` and ``calibrate-detector`` to the sub-commands."""
    s = sub.add_parser(
        "train-detector", help="train the crack network on dataset folders, export it as ONNX"
    )
    s.add_argument("datasets", nargs="+", help="folders with images/ and masks/ (255 = crack)")
    s.add_argument("--out", required=True, help="model file (.onnx); with --leave-one-out a folder")
    s.add_argument("--iterations", type=int, default=11000)
    s.add_argument("--batch", type=int, default=12)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--limit", type=int, help="use at most this many images of each set")
    s.add_argument(
        "--channels",
        type=int,
        nargs=5,
        metavar="C",
        help="the network's channels at 1/2 … 1/32 resolution (default: the shipped one's)",
    )
    s.add_argument(
        "--centre-weight",
        type=float,
        default=2.0,
        help="extra loss weight of the crack's centre line (doubled where faint)",
    )
    s.add_argument(
        "--synthetic-steel",
        type=int,
        default=0,
        metavar="N",
        help="add N rendered steel images (weld toes, bolts, edges; the simulator's)",
    )
    s.add_argument(
        "--checkpoint",
        help="save the run here every few minutes and resume from it when it exists",
    )
    s.add_argument(
        "--budget-minutes",
        type=float,
        help="stop this sitting after so many minutes (resume later with --checkpoint)",
    )
    s.add_argument(
        "--leave-one-out",
        action="store_true",
        help="one model per dataset trained on the others, as OUT/<dataset>.onnx",
    )
    s.add_argument(
        "--float", action="store_true", help="export in float (default: int8, twice as fast)"
    )
    s.set_defaults(func=cmd_train_detector)

    s = sub.add_parser(
        "calibrate-detector",
        help="fit a crack model's per-defect confidence on its sets' held-back images",
    )
    s.add_argument("datasets", nargs="+", help="the folders the model was trained on")
    s.add_argument("--model", required=True, help="the model file (.onnx), updated in place")
    s.add_argument("--synthetic-steel", type=int, default=0, metavar="N")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--limit", type=int, help="use at most this many images of each set")
    s.set_defaults(func=cmd_calibrate_detector)
