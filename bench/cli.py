"""The ``steelscan bench`` sub-command, added to the ``steelscan`` command line through the
``steelscan.commands`` entry point (the station's own packages never import the
benchmarks: they import the station)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    """Add ``bench`` to the sub-commands (``sub``: argparse's sub-parsers)."""
    s = sub.add_parser("bench", help="benchmarks against baselines measured in the same run")
    s.add_argument(
        "names",
        nargs="*",
        help="benchmarks to run: detect, stitch, map, ingest, teleop (the default set), "
        "stitch-scale, scale, robot, changes, history, map-camera, map-camera-per-axis",
    )
    s.add_argument(
        "--dataset", help="one dataset folder with images/ and masks/ (detect; default: all)"
    )
    s.add_argument(
        "--models", help="folder of leave-one-out networks, <dataset>.onnx (detect: learned)"
    )
    s.add_argument("--limit", type=int, help="use at most this many images")
    s.set_defaults(func=cmd_bench, image_work=True)


def cmd_bench(args: argparse.Namespace) -> int:
    """Run benchmarks; one JSON line per result."""
    from bench.run import run_benchmarks

    run_benchmarks(
        args.names,
        dataset=Path(args.dataset) if args.dataset else None,
        limit=args.limit,
        models=Path(args.models) if args.models else None,
    )
    return 0
