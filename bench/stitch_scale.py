"""``steelscan bench stitch-scale``: peak memory and time of ``steelscan stitch`` on long
sessions (1,000 and 10,000 frames by default), to show that memory stays bounded as the
frame count grows. Frames are rendered from an unbounded procedural painted-steel surface
into a scratch folder first; the command then runs as a separate process whose peak
resident memory is read from the operating system. Not part of the default ``bench`` run
(the 10,000-frame case takes many minutes and ~1 GB of scratch disk per 1,000 frames)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from bench.common import Result
from processing.poses import format_tum, se2_to_se3
from robot_link.sim.sweeps import LazySweep, SweepConfig

PX_PER_M = 1000.0


def write_session(folder: Path, frames: int, lanes: int, seed: int) -> LazySweep:
    """Render a lawn-mower sweep's frames (JPEG) and its odometry (TUM) into ``folder``."""
    sweep = LazySweep(SweepConfig(frames=frames, pattern="lawnmower", lanes=lanes, seed=seed))
    (folder / "frames").mkdir(parents=True)
    for k in range(len(sweep)):
        ok, buf = cv2.imencode(".jpg", sweep[k], [cv2.IMWRITE_JPEG_QUALITY, 90])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        (folder / "frames" / f"{k:06d}.jpg").write_bytes(buf.tobytes())
    T = np.array([se2_to_se3(p[0] / PX_PER_M, p[1] / PX_PER_M, p[2]) for p in sweep.odometry])
    (folder / "odometry.tum").write_text(format_tum(np.arange(len(T), dtype=float), T))
    return sweep


def _rss_mb(pid: int) -> tuple[float, float]:
    """(anonymous, file-backed) resident memory of a process in MB (Linux)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0, 0.0
    values = dict(
        line.split(":", 1)
        for line in status.splitlines()
        if line.startswith(("RssAnon", "RssFile"))
    )
    return tuple(float(values.get(k, "0 kB").split()[0]) / 1024 for k in ("RssAnon", "RssFile"))  # type: ignore[return-value]


def _run(folder: Path) -> tuple[float, float, float]:
    """Seconds and peak resident memory (anonymous; file-backed, i.e. mapped scratch files the
    kernel can drop) in MB of one ``steelscan stitch`` process, sampled every 20 ms."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "server.cli",
            "stitch",
            str(folder / "frames"),
            "--out",
            str(folder / "out"),
            "--odometry",
            str(folder / "odometry.tum"),
            "--px-per-m",
            str(PX_PER_M),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    anon = mapped = 0.0
    while proc.poll() is None:
        a, f = _rss_mb(proc.pid)
        anon, mapped = max(anon, a), max(mapped, f)
        time.sleep(0.02)
    if proc.returncode != 0:
        raise RuntimeError(
            f"steelscan stitch failed: {proc.stderr.read().decode()[-500:] if proc.stderr else ''}"
        )
    return time.perf_counter() - t0, anon, mapped


def bench_stitch_scale(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Peak memory and time per frame of whole ``steelscan stitch`` runs of growing length."""
    sizes = [1000, limit or 10000] if (limit or 10000) > 1000 else [limit or 1000]
    root = Path(tempfile.mkdtemp(prefix="steelscan-scale-"))
    try:
        baseline_mb = None
        for n in sizes:
            lanes = max(2, int(round(np.sqrt(n))))
            folder = root / str(n)
            write_session(folder, n, lanes, seed=300 + n)
            seconds, peak_mb, mapped_mb = _run(folder)
            world = json.loads((folder / "out" / "mosaic.json").read_text())
            result: Result = {
                "name": f"stitch.scale.{n}_frames.peak_memory",
                "value": round(peak_mb, 1),
                "unit": "MB",
                "ms_per_frame": round(1000 * seconds / n, 1),
                "mosaic_px": [world["width_px"], world["height_px"]],
                "pairs": world["pairs"],
                "peak_file_backed_mb": round(mapped_mb, 1),
                "note": "anonymous memory; file-backed pages are the mapped scratch image, reclaimable",
            }
            if baseline_mb is not None:
                result.update(
                    {
                        "baseline": round(baseline_mb, 1),
                        "ratio": round(peak_mb / baseline_mb, 3),
                        "baseline_is": f"{sizes[0]} frames",
                    }
                )
            baseline_mb = baseline_mb or peak_mb
            yield result
            shutil.rmtree(folder, ignore_errors=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
