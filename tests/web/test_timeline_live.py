"""The timeline of a session still being inspected, in chromium: the simulated robot's new
frames join it while the page is open, and a timeline left at its end follows them."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer
from tests.web.browser import CHROMIUM, open_dashboard, sim, wait_js, wait_until

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.one_database,  # the page only reads what REST gives
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]

TL = "document.querySelector('#timeline')"


def test_a_live_sessions_timeline_grows_and_follows(live_server: LiveServer) -> None:
    from playwright.sync_api import sync_playwright

    def live_session() -> dict | None:
        rows = httpx.get(f"{live_server.url}/api/sessions").json()["data"]
        return next((s for s in rows if s["status"] == "live" and s["frames"] >= 2), None)

    errors: list[str] = []
    robot = sim(live_server, "--exit-when-done", "--lanes", "1", "--time-scale", "2")
    try:
        with sync_playwright() as pw:
            browser, page = open_dashboard(pw, live_server.url, errors, [])
            try:
                wait_until(lambda: live_session() is not None, 60, "a live session with frames")
                sid = live_session()["id"]  # type: ignore[index]
                page.goto(f"{live_server.url}/#/session/{sid}")
                wait_js(page, f"Number({TL}?.dataset.frames || 0) >= 2")
                first = int(page.evaluate(f"{TL}.dataset.frames"))
                page.locator("#timeline-slider").fill(str(first - 1))  # at the end: follow
                wait_js(page, f"Number({TL}.dataset.frames) > {first}", timeout=60000)
                frames = int(page.evaluate(f"{TL}.dataset.frames"))
                wait_js(page, f"Number({TL}.dataset.index) >= {frames - 1}")
                seqs = [
                    f["seq"]
                    for f in httpx.get(
                        f"{live_server.url}/api/sessions/{sid}/frames", params={"limit": 1000}
                    ).json()["data"]
                ]
                index = int(page.evaluate(f"{TL}.dataset.index"))
                assert int(page.evaluate(f"{TL}.dataset.seq")) == seqs[index]
            finally:
                browser.close()
    finally:
        _, err = robot.communicate(timeout=120)
    assert robot.returncode == 0, err[-2000:]
    assert errors == []
