"""The Drive page in Debian's headless chromium against the real server and an in-process
teleoperated robot: the e-stop within reach at tablet and phone widths with a banner while
engaged, the robot's name, keys that belong to a focused control, why the robot will not
drive at the plate's edge, and a page that says so when the session ends."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from robot_link.sim.teleop import TeleopRobot, start_teleop_robot
from server.config import Settings
from tests.conftest import LiveServer
from tests.web.browser import CHROMIUM, launch, shot, wait_js, watch_errors

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


@pytest.fixture
def settings(tmp_path) -> Settings:  # type: ignore[no-untyped-def]
    return Settings(
        data_dir=tmp_path / "data",
        job_workers=1,
        auto_process=False,
        view3d=False,
        live_detect=True,
    )


@pytest.fixture
def robot(live_server: LiveServer) -> Iterator[TeleopRobot]:
    r = start_teleop_robot(live_server.url, live_server.token, seed=7)
    yield r
    r.stop(timeout_s=60)


def open_page(pw, url: str, errors: list[str], width: int, height: int):  # type: ignore[no-untyped-def]
    browser = launch(pw)
    page = browser.new_page(viewport={"width": width, "height": height})
    watch_errors(page, errors, [])
    page.goto(url + "/")
    wait_js(page, "document.querySelector('#robot-state').textContent.startsWith('robot:')")
    return browser, page


def in_view(page, selector: str) -> bool:  # type: ignore[no-untyped-def]
    box = page.locator(selector).bounding_box()
    size = page.viewport_size
    return bool(
        box
        and box["x"] >= 0
        and box["y"] >= 0
        and box["x"] + box["width"] <= size["width"]
        and box["y"] + box["height"] <= size["height"]
    )


@pytest.mark.parametrize("width,height", [(800, 1200), (390, 844)])
def test_estop_is_within_reach_at_every_width_and_a_banner_shows_it_engaged(
    live_server: LiveServer, robot: TeleopRobot, width: int, height: int
) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_page(pw, live_server.url, errors, width, height)
        assert "test-robot" in page.inner_text("#robot-state")  # its name, not a session id
        # plots with units and legends; an idle robot's speed on a small axis, not 0–100
        page.wait_for_timeout(1200)
        plots = {p["title"]: p for p in page.evaluate("window.steelscanStats.plots()")}
        assert set(plots) == {
            "speed (m/s)",
            "batteries (V)",
            "adhesion margin (× needed)",
            "ACK latency (ms)",
        }
        assert plots["speed (m/s)"]["legend"] == ["mean wheel speed"]
        assert -0.5 < plots["speed (m/s)"]["min"] < 0 < plots["speed (m/s)"]["max"] < 0.5
        page.mouse.wheel(0, 2000)  # scrolled down to the telemetry: the header stays
        page.wait_for_timeout(300)
        assert in_view(page, "#estop")
        page.click("#estop")
        page.wait_for_selector("#estop-banner:not([hidden])", timeout=5000)
        assert robot.sim.estopped
        assert "EMERGENCY STOP ENGAGED" in page.inner_text("#estop-banner")
        assert in_view(page, "#estop-banner button")
        shot(page, f"drive-estop-{width}")
        page.click("#estop-banner button")
        page.wait_for_selector("#estop-banner[hidden]", state="attached", timeout=5000)
        assert not robot.sim.estopped
        browser.close()
    assert errors == []


def test_keys_of_focused_controls_and_the_plate_edge(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    sim = robot.sim
    with sync_playwright() as pw:
        browser, page = open_page(pw, live_server.url, errors, 1440, 900)
        # a focused speed slider takes the arrows: the speed changes, the robot does not turn
        page.focus("#speed")
        for _ in range(3):
            page.keyboard.press("ArrowRight")
        assert page.input_value("#speed") == "0.11"
        assert page.inner_text("#speed-value") == "0.11 m/s"
        assert sim.w == 0.0 and sim.v == 0.0
        # Space on a focused button presses it
        page.focus("#lift-front")
        page.keyboard.press("Space")
        wait_js(
            page, "document.querySelector('#lift-front').getAttribute('aria-pressed') === 'true'"
        )
        assert sim.lift["front"]
        # at the plate's far end forward is blocked, and the page says why
        length_m, width_m = sim.structure.plate_size_m
        sim.robot.pose[:] = (length_m - 0.02, width_m / 2, 0.0)
        page.focus("body")
        page.keyboard.down("ArrowUp")
        page.wait_for_selector("#drive-blocked:not([hidden])", timeout=5000)
        notice = page.inner_text("#drive-blocked")
        assert "Forward blocked" in notice and "front left" in notice and "Reverse" in notice
        wait_js(page, "document.querySelector('#telemetry').textContent.includes('commanded 0.11')")
        shot(page, "drive-edge-blocked")
        page.keyboard.up("ArrowUp")
        wait_js(page, "document.querySelector('#drive-blocked').hidden")
        assert sim.robot.pose[0] == pytest.approx(length_m - 0.02, abs=1e-3)
        browser.close()
    assert errors == []


def test_after_the_session_ends_the_page_shows_no_stale_video_or_telemetry(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_page(pw, live_server.url, errors, 1440, 900)
        wait_js(page, "document.querySelector('#camera').dataset.live === 'true'")
        page.wait_for_selector("#telemetry dt", timeout=10000)
        if page.inner_text("#take-control") != "Release control":
            page.click("#take-control")
        wait_js(page, "document.querySelector('#take-control').textContent === 'Release control'")
        page.on("dialog", lambda d: d.accept())
        page.click("#end-session")
        wait_js(page, "document.querySelector('#camera').dataset.live === 'false'", timeout=20000)
        assert "session ended" in page.inner_text("#frame-info")
        assert page.inner_text("#video-info") == ""
        assert "no robot connected" in page.inner_text("#telemetry")
        assert "battery" not in page.inner_text("#telemetry")
        # nothing left to release: the control button offers control, disabled
        assert page.inner_text("#take-control") == "Take control"
        assert page.is_disabled("#take-control")
        for pill in ("#robot-state", "#control-state"):
            assert page.inner_text(pill) == "no robot connected"
            assert "ok" not in (page.get_attribute(pill, "class") or "")
        page.wait_for_timeout(1500)  # no late frame or sample brings the old robot back
        assert page.evaluate("document.querySelector('#camera').dataset.live") == "false"
        shot(page, "drive-session-ended")
        # a page opened now shows no robot either
        other = browser.new_page()
        other.goto(live_server.url + "/")
        wait_js(other, "document.querySelector('#link-state').classList.contains('ok')")
        other.wait_for_timeout(1000)
        assert "battery" not in other.inner_text("#telemetry")
        browser.close()
    assert errors == []


def test_the_coverage_map_shows_the_frames_and_the_gap_left_between_lanes(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    """Two lanes of frames captured from the page with a strip between them left out, the
    first over one of the simulator's cracks: the Drive page's coverage map places every
    frame, says how much is imaged, lists the one hole where the strip is and shows the
    crack found in the frames as they arrived."""
    from playwright.sync_api import sync_playwright

    sim = robot.sim
    sim.auto_capture = False
    along, across = sim.camera.footprint_m
    gap = 0.04
    crack = max(
        (d for d in sim.structure.defects if d.defect_class == "crack"), key=lambda d: d.length_m
    )
    cx, cy = crack.bbox_m[0] + crack.bbox_m[2] / 2, crack.bbox_m[1] + crack.bbox_m[3] / 2
    mount = sim.camera.mount_x_m  # frames are centred this far ahead of the robot
    spots = [(cx - mount + (i - 1.5) * along * 0.8, cy) for i in range(4)]
    spots += [(x, cy + across + gap) for x, _ in spots]
    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_page(pw, live_server.url, errors, 1440, 900)
        for i, (x, y) in enumerate(spots):
            sim.robot.pose[:] = sim.robot.odom[:] = (x, y, 0.0)
            page.wait_for_timeout(300)  # a telemetry sample at the new place
            page.click("button[data-cmd=capture]")
            wait_js(
                page, f"Number(document.querySelector('#coverage-map').dataset.frames) >= {i + 1}"
            )
        wait_js(page, "document.querySelectorAll('#coverage-holes li').length === 1")
        summary = page.inner_text("#coverage-summary")
        assert "imaged at ≤ 0.3 mm/px" in summary and "1 hole" in summary
        hole = page.inner_text("#coverage-holes li")
        y_gap = cy + across / 2 + gap / 2
        assert f"y {y_gap:.2f} m" in hole, hole
        height_cm = float(hole.split("× ")[1].split()[0])  # the strip's width, to a grid cell
        assert abs(height_cm - gap * 100) <= 1.0, hole
        wait_js(page, "Number(document.querySelector('#coverage-map').dataset.found || 0) >= 1")
        assert "seen in frames:" in page.inner_text("#coverage-summary")
        shot(page, "drive-coverage")
        browser.close()
    assert errors == []


TRAIL_PIXELS = """(() => {
  const c = document.querySelector('#coverage-map');
  const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0;
  for (let i = 0; i < px.length; i += 4)
    if (Math.abs(px[i] - 0xe0) < 12 && Math.abs(px[i + 1] - 0xa0) < 12 && Math.abs(px[i + 2] - 0x30) < 12) n++;
  return n;
})()"""


def coverage_shown(page) -> tuple[int, int, int]:  # type: ignore[no-untyped-def]
    """The coverage map's defects seen in frames, trajectory points and trajectory pixels."""
    data = page.evaluate("({...document.querySelector('#coverage-map').dataset})")
    return int(data.get("found") or 0), int(data.get("trail") or 0), page.evaluate(TRAIL_PIXELS)


def test_the_coverage_map_keeps_its_trajectory_and_defects_on_reload_and_in_a_new_tab(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    """The robot driven over a crack with two frames captured: the page reloaded, and a
    second tab opened, draw the same trajectory and the crack seen in the frames."""
    from playwright.sync_api import sync_playwright

    sim = robot.sim
    sim.auto_capture = False
    crack = max(
        (d for d in sim.structure.defects if d.defect_class == "crack"), key=lambda d: d.length_m
    )
    cx, cy = crack.bbox_m[0] + crack.bbox_m[2] / 2, crack.bbox_m[1] + crack.bbox_m[3] / 2
    along = sim.camera.footprint_m[0]
    x0 = cx - sim.camera.mount_x_m - along * 0.3
    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_page(pw, live_server.url, errors, 1440, 900)
        wait_js(page, "document.querySelector('#coverage-summary').textContent !== ''")
        for i in range(6):  # along the crack, a telemetry sample at each place
            sim.robot.pose[:] = sim.robot.odom[:] = (x0 + 0.12 * along * i, cy, 0.0)
            page.wait_for_timeout(250)
            if i in (2, 4):
                page.click("button[data-cmd=capture]")
        wait_js(page, "Number(document.querySelector('#coverage-map').dataset.found || 0) >= 1")
        wait_js(page, "Number(document.querySelector('#coverage-map').dataset.frames) >= 2")
        page.wait_for_timeout(1000)  # the second frame searched too
        found, trail, pixels = coverage_shown(page)
        assert pixels > 50  # the trajectory drawn
        summary = page.inner_text("#coverage-summary")
        assert "seen in frames:" in summary
        other = browser.new_page(viewport={"width": 1440, "height": 900})
        watch_errors(other, errors, [])
        other.goto(live_server.url + "/")
        page.reload()
        for tab in (page, other):
            wait_js(tab, "document.querySelector('#robot-state').textContent.startsWith('robot:')")
            wait_js(
                tab,
                f"Number(document.querySelector('#coverage-map').dataset.found || 0) === {found}",
            )
            wait_js(
                tab,
                f"Number(document.querySelector('#coverage-map').dataset.trail || 0) >= {trail}",
            )
            wait_js(
                tab, "document.querySelector('#coverage-summary').textContent.includes('seen in')"
            )
            assert coverage_shown(tab)[2] > 50
            assert (
                tab.inner_text("#coverage-summary").split(" · seen in frames")[1]
                == (summary.split(" · seen in frames")[1])
            )
        shot(other, "drive-coverage-new-tab")
        browser.close()
    assert errors == []
