"""``steelscan bench teleop``: teleoperation latency in the real browser against the real
server and the teleoperated simulator on loopback, over a minute of driving (``--limit``
seconds; 60 by default).

- video: frame taken at the robot (before its image is rendered) → drawn in the page's canvas;
- command: key pressed in the page (the key event's time) → its drive command received by the
  robot, and every repeated drive command sent → received;
- dead-man: the page stops sending mid-drive (a hung tab or a lost link) → the robot at a
  standstill, measured from the last drive command the robot received.

The product's targets (p99 video ≤ 150 ms, p99 command ≤ 20 ms, dead-man ≤ 300 ms) are the
baselines; ``ratio`` = measured / target (≤ 1 meets it).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.common import Result
from robot_link.sim.teleop import TeleopRobot, TeleopSim, start_teleop_robot

if TYPE_CHECKING:
    from playwright.sync_api import Page

    from server.loopback import BackgroundServer

TARGETS_MS = {"video_p99": 150.0, "command_p99": 20.0, "deadman_max": 300.0}
PATTERN = [
    ("ArrowUp", 1.0),
    (None, 0.4),
    ("ArrowLeft", 0.5),
    (None, 0.3),
    ("ArrowDown", 1.0),
    (None, 0.4),
    ("ArrowRight", 0.5),
    (None, 0.3),
]
DEADMAN_TRIALS = 10


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if values else float("nan")


def _start_station(seconds: float) -> tuple[Path, BackgroundServer, TeleopRobot]:
    """A station in a scratch folder on loopback with one robot account, and the teleoperated
    simulator connected to it for the drive, the dead-man trials and a margin."""
    from server.config import Settings
    from server.link.robots import create_robot
    from server.loopback import BackgroundServer, free_port
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    scratch = Path(tempfile.mkdtemp(prefix="steelscan-bench-teleop-"))
    settings = Settings(data_dir=scratch, auto_process=False, view3d=False, job_workers=1)
    upgrade(settings.resolved_database_url())
    engine = make_engine(settings.resolved_database_url())
    token = create_robot(make_sessionmaker(engine), "bench-teleop")
    engine.dispose()
    server = BackgroundServer(settings, free_port())
    server.start()
    robot = start_teleop_robot(server.url, token, duration_s=seconds + 30 + DEADMAN_TRIALS * 2)
    return scratch, server, robot


def drive_keys(page: Page, seconds: float) -> None:
    """Press and release the keys of ``PATTERN`` in turn for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key, hold in PATTERN:
            if key:
                page.keyboard.down(key)
            time.sleep(hold)
            if key:
                page.keyboard.up(key)


def _deadman_trials(page: Page) -> None:
    """``DEADMAN_TRIALS`` times: the page stops sending while a key is held (the robot must
    stop by itself), then sends again and drives back."""
    for _ in range(DEADMAN_TRIALS):
        page.keyboard.down("ArrowUp")
        time.sleep(0.5)
        page.evaluate("window.steelscanStats.mute = true")
        time.sleep(0.6)
        page.keyboard.up("ArrowUp")
        page.evaluate("window.steelscanStats.mute = false")
        page.keyboard.down("ArrowDown")
        time.sleep(0.5)
        page.keyboard.up("ArrowDown")
        time.sleep(0.3)


@contextmanager
def open_dashboard(chromium: str, url: str) -> Iterator[Page]:
    """The dashboard at ``url`` in headless ``chromium``, once it has drawn 10 video frames."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=chromium,
            headless=True,
            args=[
                "--no-sandbox",
                "--disable-gpu",
                "--disable-background-networking",
                "--disable-sync",
            ],
        )
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(url + "/")
        # polled from outside: the page's content security policy forbids wait_for_function
        deadline = time.monotonic() + 60
        while not page.evaluate(
            "Number(document.querySelector('#camera').dataset.frames || 0) >= 10"
        ):
            if time.monotonic() > deadline:
                raise RuntimeError("the dashboard drew no live video within 60 s")
            page.wait_for_timeout(100)
        try:
            yield page
        finally:
            browser.close()


def _drive_in_browser(chromium: str, url: str, sim: TeleopSim, seconds: float) -> list[float]:
    """Drive the simulated robot from the dashboard for ``seconds``, then run the dead-man
    trials; the video latencies of the drive (ms, one per frame drawn). The robot's log
    ``sim.log`` holds the command, key and dead-man latencies of the drive."""
    with open_dashboard(chromium, url) as page:
        page.evaluate("window.steelscanStats.video.length = 0")
        sim.log.command_latency_ms.clear()
        sim.log.key_latency_ms.clear()
        drive_keys(page, seconds)
        video = list(page.evaluate("window.steelscanStats.video"))
        sim.log.deadman_stops_ms.clear()
        _deadman_trials(page)
    return video


def latency_results(
    name: str, values: list[float], target: float, base: dict[str, float]
) -> Iterator[Result]:
    """The p50 and the p99 (against ``target``) of the latencies ``values`` (ms)."""
    p99 = _pct(values, 99)
    yield {
        "name": f"{name}_p50",
        "value": round(_pct(values, 50), 2),
        "unit": "ms",
        "samples": len(values),
        **base,
    }
    yield {
        "name": f"{name}_p99",
        "value": round(p99, 2),
        "unit": "ms",
        "baseline": target,
        "baseline_is": "target",
        "ratio": round(p99 / target, 3),
        "samples": len(values),
        **base,
    }


def _deadman_result(deadman: list[float]) -> Result:
    """The slowest dead-man stop (ms) against its target, and the median."""
    worst = max(deadman) if deadman else float("nan")
    return {
        "name": "teleop_deadman_stop_max",
        "value": round(worst, 1),
        "unit": "ms",
        "baseline": TARGETS_MS["deadman_max"],
        "baseline_is": "target",
        "ratio": round(worst / TARGETS_MS["deadman_max"], 3),
        "trials": len(deadman),
        "p50": round(_pct(deadman, 50), 1),
    }


def bench_teleop(*, dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Drive the simulated robot from the browser for a minute; latencies p50/p99 and the dead-man stop."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        yield {
            "name": "teleop",
            "value": None,
            "unit": "",
            "error": "Debian's chromium is not installed (scripts/setup.sh installs it)",
        }
        return
    seconds = float(limit or 60)
    scratch, server, robot = _start_station(seconds)
    try:
        sim = robot.sim
        video = _drive_in_browser(chromium, server.url, sim, seconds)
        commands, keys, deadman = (
            list(sim.log.command_latency_ms),
            list(sim.log.key_latency_ms),
            list(sim.log.deadman_stops_ms),
        )
    finally:
        robot.stop()
        server.stop()
        shutil.rmtree(scratch, ignore_errors=True)
    base = {"seconds": seconds}
    for name, values, target in (
        ("teleop_video_latency", video, TARGETS_MS["video_p99"]),
        ("teleop_key_to_robot_latency", keys, TARGETS_MS["command_p99"]),
        ("teleop_command_latency", commands, TARGETS_MS["command_p99"]),
    ):
        yield from latency_results(name, values, target, base)
    yield {
        "name": "teleop_video_fps",
        "value": round(len(video) / seconds, 1),
        "unit": "frames/s",
        **base,
    }
    yield _deadman_result(deadman)
    from bench.robot import key_to_mcu

    yield from key_to_mcu(chromium, min(seconds, 30.0))
