"""The Drive page as each user leaves it, in chromium against the real server and a
teleoperated robot: plots of any telemetry field the robot sends (in the units its keys
name), and panels opened or closed, both kept with the user's preferences on the station
so a reload (or another browser) shows the page the same."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from robot_link.sim.teleop import TeleopRobot, start_teleop_robot
from server.config import Settings
from tests.conftest import LiveServer
from tests.web.browser import CHROMIUM, launch, wait_js, watch_errors

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


@pytest.fixture
def settings(tmp_path) -> Settings:  # type: ignore[no-untyped-def]
    return Settings(data_dir=tmp_path / "data", job_workers=1, auto_process=False, view3d=False)


@pytest.fixture
def robot(live_server: LiveServer) -> Iterator[TeleopRobot]:
    r = start_teleop_robot(live_server.url, live_server.token, seed=5)
    yield r
    r.stop(timeout_s=60)


def test_any_field_is_plotted_and_the_layout_is_kept(
    live_server: LiveServer, robot: TeleopRobot
) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    field = "battery_v.logic"
    with sync_playwright() as pw:
        browser = launch(pw)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        watch_errors(page, errors, [])
        try:
            page.goto(live_server.url + "/")
            wait_js(page, "document.querySelector('#robot-state').textContent.startsWith('robot:')")
            page.click("#live-fields summary")
            box = page.locator(f"#live-field-list input[value='{field}']")
            box.wait_for(timeout=20000)
            names = page.locator("#live-field-list label").all_inner_texts()
            assert "wheel_speed_mps[0] (m/s)" in [n.strip() for n in names]
            assert "link.ack_latency_ms (ms)" in [n.strip() for n in names]
            box.check()
            wait_js(page, f"document.querySelector('#live-plots').dataset.fields === '{field}'")
            wait_js(page, "Number(document.querySelector('#live-plots').dataset.points) >= 3")
            title = page.inner_text("#live-plots .u-title")
            assert title == f"{field} (V)"
            # close the coverage panel; both choices are the user's, on the station
            page.click("details.panel[data-panel='coverage'] > summary")
            wait_js(page, "JSON.parse(document.body.dataset.panels).coverage === 'closed'")
            prefs_url = f"{live_server.url}/api/auth/me/preferences"
            for _ in range(50):
                prefs = httpx.get(prefs_url).json()
                if prefs.get("drive_panels", {}).get("coverage") == "closed":
                    break
                page.wait_for_timeout(100)
            assert prefs["drive_plot_fields"] == [field]
            assert prefs["drive_panels"] == {"plots": "open", "coverage": "closed", "edges": "open"}
            # another browser page of the same user: the same layout, the same plot
            other = browser.new_page(viewport={"width": 1280, "height": 900})
            watch_errors(other, errors, [])
            other.goto(live_server.url + "/")
            wait_js(other, f"document.querySelector('#live-plots').dataset.fields === '{field}'")
            wait_js(other, "document.body.dataset.panels !== undefined")
            assert not other.locator("details.panel[data-panel='coverage']").evaluate("d => d.open")
            assert other.locator("details.panel[data-panel='plots']").evaluate("d => d.open")
            wait_js(other, "Number(document.querySelector('#live-plots').dataset.points) >= 3")
        finally:
            browser.close()
    assert errors == []
