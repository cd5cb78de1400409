"""The benchmarks by name and how they run: each result is one JSON line with ``name``,
``value``, ``unit`` and, where there is a baseline, ``baseline`` and ``ratio``."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

from bench.changes import bench_changes
from bench.common import Result
from bench.detect import bench_detect
from bench.history import bench_history
from bench.ingest import bench_ingest
from bench.map import bench_map
from bench.map_camera import bench_map_camera
from bench.robot import bench_robot
from bench.scale import bench_scale
from bench.stitch import bench_stitch
from bench.stitch_scale import bench_stitch_scale
from bench.teleop import bench_teleop
from server.errors import CommandError

BENCHMARKS: dict[str, Callable[..., Iterator[Result]]] = {
    "detect": bench_detect,
    "stitch": bench_stitch,
    "map": bench_map,
    "map-camera": bench_map_camera,
    "map-camera-per-axis": partial(bench_map_camera, per_axis=True),
    "ingest": bench_ingest,
    "stitch-scale": bench_stitch_scale,
    "teleop": bench_teleop,
    "scale": bench_scale,
    "robot": bench_robot,
    "changes": bench_changes,
    "history": bench_history,
}
DEFAULT = [
    "detect",
    "stitch",
    "map",
    "ingest",
    "teleop",
]  # the others take many minutes: run them by name


def run_benchmarks(
    names: list[str],
    *,
    dataset: Path | None = None,
    limit: int | None = None,
    models: Path | None = None,
) -> None:
    """Run the named benchmarks (all when empty), printing one JSON object per line."""
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise CommandError(f"unknown benchmark(s) {unknown}; known: {sorted(BENCHMARKS)}")
    for name in names or DEFAULT:
        extra = {"models": models} if name == "detect" else {}
        for result in BENCHMARKS[name](dataset=dataset, limit=limit, **extra):
            print(json.dumps(result), flush=True)
