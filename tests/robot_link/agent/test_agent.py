"""The on-board agent (``steelscan robot``) against the MCU emulator on a pty and a real
station: a whole autonomous sweep that leaves no hole and crosses no edge, frames at the
required spacing; the robot at rest within 0.5 s when the station dies mid-sweep; an
operator's take-over, e-stop and resume mid-sweep; a bad config or a silent MCU refused."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from robot_link.emulator.coverage import footprint_coverage
from robot_link.emulator.process import EmulatorProcess
from server.config import Settings
from server.loopback import free_port
from tests.conftest import LiveServer, make_token

pytestmark = pytest.mark.one_database

FAST_SWEEP = """
[sweep]
speed_mps = 0.2
turn_radps = 1.0
[safety]
max_speed_mps = 0.25
max_turn_radps = 1.2
"""


@pytest.fixture
def settings(tmp_path: Path, database_url: str) -> Settings:
    return Settings(data_dir=tmp_path / "data", job_workers=1, auto_process=False, view3d=False)


def write_config(path: Path, url: str, token: str, device: str, extra: str = "") -> Path:
    path.write_text(
        f'[station]\nurl = "{url}"\ntoken = "{token}"\n[mcu]\ndevice = "{device}"\n'
        '[camera]\nsource = "emulator"\n[tof]\nsource = "emulator"\n' + extra
    )
    return path


def run_robot(config: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "server.cli", "robot", "--config", str(config), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_a_sweep_covers_the_plate_without_crossing_an_edge(
    live_server: LiveServer, emulator_factory, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    emu: EmulatorProcess = emulator_factory("--seed", "31", "--plate", "0.6x0.5")
    config = write_config(
        tmp_path / "robot.toml", live_server.url, live_server.token, emu.device, FAST_SWEEP
    )
    robot = run_robot(config, "--sweep")
    out, err = robot.communicate(timeout=240)
    assert robot.returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["sweep_finished"] and summary["lanes"] >= 2
    states = [s for _, s in emu.states]
    assert all(s["on_plate"] for s in states)
    coverage, _ = footprint_coverage(emu.header, states)
    assert coverage >= 0.99
    # every frame is stored, each within the capture spacing of Hall distance of the last
    session = httpx.get(f"{live_server.url}/api/sessions/{summary['session_id']}").json()
    assert session["frames"] == summary["frames_sent"] and session["clouds"] >= 1
    frames = httpx.get(f"{live_server.url}/api/sessions/{summary['session_id']}/coverage").json()[
        "frames"
    ]
    assert len(frames) == summary["frames_sent"]
    centres = np.array([np.mean(f["footprint"], axis=0) for f in frames])
    spacing = emu.header["camera_footprint"]["height"] * (1 - 0.3)
    assert np.linalg.norm(np.diff(centres, axis=0), axis=1).max() <= spacing + 0.02


def test_the_robot_is_at_rest_within_half_a_second_when_the_station_dies(
    emulator: EmulatorProcess, tmp_path: Path
) -> None:
    settings = Settings(data_dir=tmp_path / "data")
    token = make_token(settings)
    port = free_port()
    station = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "server.cli",
            "serve",
            "--data-dir",
            str(tmp_path / "data"),
            "--port",
            str(port),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    robot = None
    try:
        url = f"http://127.0.0.1:{port}"
        for _ in range(100):
            try:
                httpx.get(f"{url}/api/health", timeout=1)
                break
            except httpx.HTTPError:
                time.sleep(0.2)
        robot = run_robot(
            write_config(tmp_path / "robot.toml", url, token, emu_dev(emulator)), "--sweep"
        )
        emulator.wait_for(lambda s: abs(s["speed"]) > 0.1, 30)
        station.kill()
        killed = time.monotonic()
        station.wait()
        time.sleep(1.0)
        after = [(t, s) for t, s in emulator.states if t > killed]
        rest = next(t for t, s in after if s["speed"] == 0.0)
        assert rest - killed <= 0.5
        assert all(s["speed"] == 0.0 for t, s in after if t > rest)
        assert all(s["on_plate"] for _, s in emulator.states)
    finally:
        station.kill()
        if robot is not None:
            robot.send_signal(signal.SIGINT)
            robot.wait(20)


def emu_dev(emulator: EmulatorProcess) -> str:
    return emulator.device


def _browser_command(ws, sid: str, cmd: str, **args: object) -> None:  # type: ignore[no-untyped-def]
    ws.send(
        json.dumps({"session_id": sid, "cmd": cmd, "args": {**args, "sent_ms": time.time() * 1000}})
    )


def test_an_operator_takes_over_stops_and_resumes_a_sweep(
    live_server: LiveServer, emulator: EmulatorProcess, tmp_path: Path
) -> None:
    from websockets.sync.client import connect

    config = write_config(
        tmp_path / "robot.toml", live_server.url, live_server.token, emulator.device
    )
    robot = run_robot(config, "--sweep")
    try:
        with connect(live_server.url.replace("http", "ws") + "/ws/live", max_size=2**22) as ws:
            sid = None
            deadline = time.monotonic() + 30
            while sid is None and time.monotonic() < deadline:
                e = ws.recv(timeout=5)
                if (
                    isinstance(e, str)
                    and (m := json.loads(e)).get("type") == "robot"
                    and m["connected"]
                ):
                    sid = m["session_id"]
            assert sid is not None
            emulator.wait_for(lambda s: s["speed"] > 0.05, 30)
            # take-over: the operator reverses; the sweep pauses, the dead-man then stops it
            for _ in range(10):
                _browser_command(ws, sid, "drive", linear_mps=-0.05, angular_radps=0.0)
                time.sleep(0.05)
            emulator.wait_for(lambda s: s["speed"] < 0, 2)
            emulator.wait_for(lambda s: s["speed"] == 0.0, 2)
            time.sleep(1.0)
            assert all(s["speed"] == 0.0 for t, s in emulator.states[-5:])
            # resume the sweep; then the e-stop stops it and refuses driving until resumed
            _browser_command(ws, sid, "sweep", action="resume")
            emulator.wait_for(lambda s: s["speed"] != 0.0, 5)
            _browser_command(ws, sid, "estop")
            stopped = emulator.wait_for(lambda s: s["speed"] == 0.0 and s["estop"], 1)
            _browser_command(ws, sid, "drive", linear_mps=0.1, angular_radps=0.0)
            time.sleep(0.5)
            assert all(s["speed"] == 0.0 for _, s in emulator.states[-3:])
            _browser_command(ws, sid, "resume")
            _browser_command(ws, sid, "sweep", action="start")
            emulator.wait_for(lambda s: s["speed"] != 0.0 and s["t"] > stopped["t"], 5)
            _browser_command(ws, sid, "sweep", action="stop")
            emulator.wait_for(lambda s: s["speed"] == 0.0, 2)
            _browser_command(ws, sid, "end_session")
        out, err = robot.communicate(timeout=60)
        assert robot.returncode == 0, err
        assert all(s["on_plate"] for _, s in emulator.states)
    finally:
        if robot.poll() is None:
            robot.kill()


def test_a_bad_config_or_a_silent_mcu_exits_with_one_error_line(
    emulator: EmulatorProcess, tmp_path: Path
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[station]\nurl = 1\n")
    robot = run_robot(bad)
    _, err = robot.communicate(timeout=60)
    assert (
        robot.returncode != 0
        and err.strip().startswith("error:")
        and len(err.strip().splitlines()) == 1
    )
    emulator.signal(signal.SIGUSR1)
    time.sleep(0.3)  # the emulator's loop takes the signal within a tick
    robot = run_robot(
        write_config(tmp_path / "robot.toml", "http://127.0.0.1:9", "t", emulator.device)
    )
    _, err = robot.communicate(timeout=60)
    assert robot.returncode != 0 and "did not answer" in err and "Traceback" not in err
