"""Driving from the dashboard in Debian's headless chromium against the real server and a
teleoperated simulated robot: by keyboard with the dead-man stop, e-stop, one driver per
robot, and by gamepad. Screenshots of each page go to the test's output folder."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.conftest import LiveServer
from tests.web.browser import (
    CHROMIUM,
    drove_on,
    latest_telemetry,
    launch,
    open_dashboard,
    shot,
    sim,
    stood_still,
    wait_js,
    wait_until,
    watch_errors,
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


@pytest.fixture
def teleop_robot(
    live_server: LiveServer, tmp_path: Path
) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A teleoperated simulated robot, connected, and its session id."""
    log = tmp_path / "teleop-robot.log"
    robot = sim(live_server, "--teleop", "--duration", "120", "--exit-when-done", log=log)
    try:

        def session() -> str | None:
            rows = httpx.get(f"{live_server.url}/api/sessions").json()["data"]
            return rows[0]["id"] if rows else None

        def started() -> bool:
            if robot.poll() is not None:
                raise AssertionError(f"the teleop robot exited: {log.read_text()[-2000:]}")
            return session() is not None

        wait_until(started, 60, "the teleop session")
        yield robot, str(session())
    finally:
        robot.terminate()
        robot.wait(timeout=30)


@pytest.mark.one_database  # driving stores nothing a test on both databases does not
def test_drive_by_keyboard_with_deadman_estop_and_one_driver(
    live_server: LiveServer, teleop_robot: tuple
) -> None:
    from playwright.sync_api import sync_playwright

    _, sid = teleop_robot
    url = live_server.url
    errors: list[str] = []
    foreign: list[str] = []

    with sync_playwright() as pw:
        browser, page = open_dashboard(pw, url, errors, foreign)
        # live video
        wait_js(
            page,
            "Number(document.querySelector('#camera').dataset.frames || 0) >= 10",
            timeout=60000,
        )
        x0 = latest_telemetry(url, sid)["pose"]["x"]
        # a held key drives the robot and the telemetry shows it
        page.keyboard.down("ArrowUp")
        wait_js(
            page,
            "document.querySelector('#telemetry').textContent.includes('0.08 · turn')",
            timeout=5000,
        )
        time.sleep(1.0)
        assert page.inner_text("#control-state") == "you drive"
        shot(page, "drive-teleop")
        released = time.time()  # the simulated robot stamps its telemetry with this clock
        page.keyboard.up("ArrowUp")
        wait_until(lambda: stood_still(url, sid, released), 5, "the robot to stop on key release")
        assert latest_telemetry(url, sid)["pose"]["x"] > x0 + 0.05
        # under a second's worth of driving after the key goes up (a stalled simulator adds none)
        moved, speed = drove_on(url, sid, released)
        assert speed > 0 and moved < speed * 1.0
        # e-stop: the robot stops and refuses to drive until the e-stop is reset
        page.keyboard.down("ArrowUp")
        time.sleep(0.5)
        page.click("#estop")
        wait_until(lambda: latest_telemetry(url, sid)["estop"], 2, "the e-stop")
        page.keyboard.up("ArrowUp")
        page.keyboard.down("ArrowUp")
        time.sleep(0.5)
        assert latest_telemetry(url, sid)["drive"]["linear_mps"] == 0.0
        wait_js(
            page,
            "document.querySelector('#command-result').textContent.includes('emergency stop')",
            timeout=5000,
        )
        # held on, and let go, the page keeps saying why the robot does not move
        for _ in range(8):
            page.wait_for_timeout(100)
            assert "refused" in page.inner_text("#command-result")
        page.keyboard.up("ArrowUp")
        page.wait_for_timeout(400)
        assert "emergency stop" in page.inner_text("#command-result")
        page.click("button[data-cmd=resume]")
        wait_until(lambda: not latest_telemetry(url, sid)["estop"], 2, "the e-stop reset")
        # a second operator's page watches, may not drive, may stop
        other = browser.new_page()
        watch_errors(other, errors, foreign)
        other.goto(url + "/")
        wait_js(
            other,
            "document.querySelector('#control-state').textContent.startsWith('driven by')",
            timeout=20000,
        )
        other.focus("body")
        other.keyboard.down("ArrowUp")
        wait_js(
            other,
            "document.querySelector('#command-result').textContent.includes('driven by')",
            timeout=5000,
        )
        other.keyboard.up("ArrowUp")
        assert latest_telemetry(url, sid)["drive"]["linear_mps"] == 0.0
        # the driver's page closes while driving: the robot stops
        page.keyboard.down("ArrowUp")
        wait_until(
            lambda: latest_telemetry(url, sid)["drive"]["linear_mps"] > 0, 3, "driving again"
        )
        page.close()
        wait_until(
            lambda: latest_telemetry(url, sid)["drive"]["linear_mps"] == 0.0,
            2,
            "the robot to stop when its driver's page closed",
        )
        wait_js(
            other,
            "document.querySelector('#control-state').textContent === 'nobody drives'",
            timeout=5000,
        )
        other.close()
        browser.close()
    assert errors == []
    assert foreign == []


@pytest.mark.one_database
def test_a_gamepad_drives_and_its_b_button_stops(
    live_server: LiveServer, teleop_robot: tuple
) -> None:
    """The Gamepad API, faked in the page before it loads: the left stick pushed forward
    drives the robot, letting go stops it."""
    from playwright.sync_api import sync_playwright

    _, sid = teleop_robot
    url = live_server.url
    with sync_playwright() as pw:
        browser = launch(pw)
        page = browser.new_page()
        page.add_init_script("""
            window.fakePad = { axes: [0, 0, 0, 0], buttons: Array.from({ length: 16 }, () => ({ pressed: false, value: 0 })) };
            navigator.getGamepads = () => [window.fakePad];
        """)
        page.goto(url + "/")
        wait_js(
            page,
            "document.querySelector('#robot-state').textContent.startsWith('robot:')",
            timeout=30000,
        )
        page.evaluate("window.fakePad.axes[1] = -1")  # stick forward
        wait_until(
            lambda: latest_telemetry(url, sid)["drive"]["linear_mps"] > 0.05,
            3,
            "the gamepad to drive",
        )
        page.evaluate("window.fakePad.axes[1] = 0")  # let go
        wait_until(
            lambda: latest_telemetry(url, sid)["drive"]["linear_mps"] == 0.0,
            2,
            "the robot to stop when the stick is let go",
        )
        page.evaluate("window.fakePad.axes[0] = -1")  # stick left: turn left
        yaw0 = latest_telemetry(url, sid)["pose"]["yaw"]
        wait_until(  # yaw about z into the surface (y to the robot's right): a left turn is < 0
            lambda: latest_telemetry(url, sid)["drive"]["angular_radps"] < -0.1,
            3,
            "the gamepad to turn",
        )
        wait_until(
            lambda: latest_telemetry(url, sid)["pose"]["yaw"] < yaw0 - 0.02,
            3,
            "the robot's heading to turn to its left",
        )
        # B: stop, whatever the stick says
        page.evaluate("window.fakePad.buttons[1].pressed = true")
        wait_until(
            lambda: latest_telemetry(url, sid)["drive"]["angular_radps"] == 0.0,
            2,
            "B to stop the robot",
        )
        browser.close()
