"""``steelscan bench robot``: the on-board agent with the MCU emulator on a pty.

- sweep: an autonomous sweep (``steelscan robot --sweep``) on each of ``SEEDS`` (plates,
  defects and start poses nobody tuned on), judged from the emulator's true states alone:
  the plate's fraction inside the camera footprint at some moment (target 99 %), any wheel
  off the plate (target: never), the time it took;
- edge stop: the firmware alone (no host, no link) driving at a plate's edge from several
  headings and speeds: IR sensor sees no surface → wheels at rest (target 100 ms).

``steelscan bench teleop`` adds the key → MCU wheel command latency (:func:`key_to_mcu`).
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench.common import Result

if TYPE_CHECKING:
    from server.loopback import BackgroundServer

SEEDS = (7101, 7202, 7303)
COVERAGE_TARGET = 0.99
EDGE_STOP_TARGET_MS = 100.0


def scratch_station(name: str) -> tuple[Path, BackgroundServer, str]:
    """A station in a scratch folder on loopback, and a robot token for it."""
    from server.config import Settings
    from server.link.robots import create_robot
    from server.loopback import BackgroundServer, free_port
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    scratch = Path(tempfile.mkdtemp(prefix=f"steelscan-bench-{name}-"))
    settings = Settings(data_dir=scratch, auto_process=False, view3d=False, job_workers=1)
    upgrade(settings.resolved_database_url())
    engine = make_engine(settings.resolved_database_url())
    token = create_robot(make_sessionmaker(engine), f"bench-{name}")
    engine.dispose()
    server = BackgroundServer(settings, free_port())
    server.start()
    return scratch, server, token


def robot_toml(path: Path, url: str, token: str, device: str) -> Path:
    """A robot.toml for the emulator's camera and ToF, everything else at its defaults."""
    path.write_text(
        f'[station]\nurl = "{url}"\ntoken = "{token}"\n[mcu]\ndevice = "{device}"\n'
        '[camera]\nsource = "emulator"\n[tof]\nsource = "emulator"\n'
    )
    return path


def _sweep(seed: int, url: str, token: str, folder: Path) -> dict[str, Any]:
    from robot_link.emulator.coverage import footprint_coverage
    from robot_link.emulator.process import start_emulator

    emu = start_emulator("--seed", str(seed))
    try:
        config = robot_toml(folder / f"robot-{seed}.toml", url, token, emu.device)
        t0 = time.monotonic()
        run = subprocess.run(
            [sys.executable, "-m", "server.cli", "robot", "--config", str(config), "--sweep"],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        seconds = time.monotonic() - t0
    finally:
        emu.stop()
    states = [s for _, s in emu.states]
    coverage, _ = footprint_coverage(emu.header, states)
    return {
        "seed": seed,
        "plate_m": [emu.header["plate"]["width"], emu.header["plate"]["height"]],
        "coverage": coverage,
        "on_plate": all(s["on_plate"] for s in states),
        "seconds": round(seconds, 1),
        "exit": run.returncode,
        "error": run.stderr.strip().splitlines()[-1] if run.returncode else None,
    }


def sweep_results(seeds: tuple[int, ...]) -> Iterator[Result]:
    """One result per seed, then the worst and the mean coverage."""
    scratch, server, token = scratch_station("robot")
    runs = []
    try:
        for seed in seeds:
            run = _sweep(seed, server.url, token, scratch)
            runs.append(run)
            yield {
                "name": "robot.sweep.coverage",
                "value": round(100 * run["coverage"], 3),
                "unit": "%",
                "baseline": 100 * COVERAGE_TARGET,
                "baseline_is": "target",
                "ratio": round(run["coverage"] / COVERAGE_TARGET, 4),
                **{k: v for k, v in run.items() if k != "coverage"},
            }
    finally:
        server.stop()
        shutil.rmtree(scratch, ignore_errors=True)
    values = [r["coverage"] for r in runs]
    yield {
        "name": "robot.sweep.coverage_worst",
        "value": round(100 * min(values), 3),
        "unit": "%",
        "baseline": 100 * COVERAGE_TARGET,
        "baseline_is": "target",
        "ratio": round(min(values) / COVERAGE_TARGET, 4),
        "mean": round(100 * float(np.mean(values)), 3),
        "wheels_stayed_on": all(r["on_plate"] for r in runs),
        "seeds": list(seeds),
    }


def edge_stop_ms(speed_mps: float, heading: float, seed: int = 0) -> float:
    """Firmware alone, a host driving straight at the edge at ``speed_mps``: the time from
    the first IR sensor without surface to the wheels at rest (ms)."""
    from robot_link.emulator.firmware import Firmware
    from robot_link.emulator.world import make_world
    from robot_link.mcu.packets import Drive, PacketType

    world = make_world(seed, (1.0, 0.8))
    world.robot.pose[:] = (0.5, 0.4, heading)
    fw = Firmware(world)
    out_at = None
    for i in range(3000):
        if i % 2 == 0:
            fw.handle(PacketType.DRIVE, 1, Drive(speed_mps, speed_mps, 0.2).pack())
        fw.tick(0.01)
        if out_at is None and fw.ir_out():
            out_at = fw.t_s
        if out_at is not None and fw.wheels == (0.0, 0.0):
            if not world.wheels_on_plate():
                return math.inf
            return (fw.t_s - out_at) * 1000
    return math.inf


def edge_results() -> Iterator[Result]:
    """The slowest edge stop over headings and speeds."""
    trials = [
        edge_stop_ms(v, h, seed)
        for seed, v in enumerate((0.08, 0.12, 0.15, 0.25))
        for h in np.radians((0, 20, 45, 70, 90, 135, 180, -60))
    ]
    worst = max(trials)
    yield {
        "name": "robot.edge_stop_max",
        "value": round(worst, 1),
        "unit": "ms",
        "baseline": EDGE_STOP_TARGET_MS,
        "baseline_is": "target",
        "ratio": round(worst / EDGE_STOP_TARGET_MS, 3),
        "trials": len(trials),
        "p50": round(float(np.median(trials)), 1),
    }


def bench_robot(*, dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Sweeps on ``limit`` seeds (all of SEEDS by default) and the edge stop."""
    yield from edge_results()
    yield from sweep_results(SEEDS[: limit or len(SEEDS)])


def key_to_mcu(chromium: str, seconds: float) -> Iterator[Result]:
    """Drive the on-board agent (MCU emulator behind it) from the dashboard with the keys
    for ``seconds``: key event in the page → DRIVE written to the MCU's serial line."""
    from bench.teleop import drive_keys, latency_results, open_dashboard
    from robot_link.agent.background import start_agent
    from robot_link.agent.config import load_config
    from robot_link.emulator.process import start_emulator

    scratch, server, token = scratch_station("teleop-robot")
    emu = start_emulator("--seed", "11", "--plate", "2.0x1.2")
    try:
        agent = start_agent(
            load_config(robot_toml(scratch / "robot.toml", server.url, token, emu.device))
        )
        try:
            with open_dashboard(chromium, server.url) as page:
                agent.agent.control.log.key_to_mcu_ms.clear()
                drive_keys(page, seconds)
            keys = list(agent.agent.control.log.key_to_mcu_ms)
        finally:
            agent.stop()
    finally:
        emu.stop()
        server.stop()
        shutil.rmtree(scratch, ignore_errors=True)
    yield from latency_results("teleop_key_to_mcu_latency", keys, 20.0, {"seconds": seconds})
