"""Every page of the dashboard fits the window's width, from a phone held upright to a
desktop: nothing scrolls sideways (a robot with a long name connected, the processed
inspection's review page with its mosaic and defect table)."""

from __future__ import annotations

import uuid

import httpx
import pytest

from robot_link.protocol import decode_message
from server.config import Settings
from tests.conftest import LiveServer, make_token
from tests.server.helpers import robot_ws, start
from tests.web.browser import CHROMIUM, launch, watch_errors

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.one_database,  # only the layout is under test
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]

WIDTHS = (360, 390, 800, 1024, 1440)
LONG_NAME = "north-span-crawler-with-a-long-name-07"
# the elements reaching past the window's right edge, the deepest first (what to fix)
OVERFLOWING = """() => [...document.querySelectorAll('body *')]
  .filter(e => e.getBoundingClientRect().right > window.innerWidth + 0.5 && e.offsetParent)
  .reverse().slice(0, 6)
  .map(e => `${e.tagName.toLowerCase()}${e.id ? '#' + e.id : ''}.${e.className}`
    + ` ${Math.round(e.getBoundingClientRect().right)}`)"""


# the mosaic viewer's zoom buttons that the legend (or anything laid over the mosaic) covers
COVERED_BUTTONS = """() => {
  const legend = document.querySelector('.mosaic-legend').getBoundingClientRect();
  return [...document.querySelectorAll('#mosaic-viewer [title]')]
    .filter(b => ['Zoom in', 'Zoom out', 'Go home', 'Toggle full page'].includes(b.title))
    .filter(b => { const r = b.getBoundingClientRect();
      return r.width > 0 && r.left < legend.right && legend.left < r.right
        && r.top < legend.bottom && legend.top < r.bottom; })
    .map(b => b.title)}"""


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"auto_process": False, "view3d": False})


def widths_over(page, url: str, ready: str) -> list[str]:  # type: ignore[no-untyped-def]
    """The page at each width (opened at the narrowest, then widened): what scrolls
    sideways."""
    wrong = []
    page.set_viewport_size({"width": WIDTHS[0], "height": 800})
    page.goto(url)
    page.reload()
    page.wait_for_selector(ready, state="attached", timeout=20000)
    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 800})
        page.wait_for_timeout(200)
        scroll = page.evaluate("document.documentElement.scrollWidth")
        inner = page.evaluate("window.innerWidth")
        if scroll > inner:
            wrong.append(f"{url} at {width} px: {scroll} px wide {page.evaluate(OVERFLOWING)}")
    return wrong


def test_no_page_scrolls_sideways_at_any_width(
    inspected: tuple[LiveServer, str], live_server: LiveServer
) -> None:
    from playwright.sync_api import sync_playwright

    live, sid = inspected
    errors: list[str] = []
    with (
        sync_playwright() as pw,
        robot_ws(live_server, make_token(live_server.settings, LONG_NAME)) as robot,
    ):
        robot.send(start(uuid.uuid4()))
        decode_message(robot.recv(timeout=10))
        browser = launch(pw)
        page = browser.new_page()
        watch_errors(page, errors, [])
        try:
            page.goto(f"{live_server.url}/#/drive")
            page.wait_for_selector("#robot-select option", state="attached", timeout=15000)
            assert LONG_NAME in page.inner_text("#robot-select")
            wrong = widths_over(page, f"{live_server.url}/#/drive", "#robot-select option")
            wrong += widths_over(page, f"{live_server.url}/#/admin", "#robots tr[data-robot]")
            wrong += widths_over(page, f"{live.url}/#/sessions", "#sessions tbody tr")
            wrong += widths_over(page, f"{live.url}/#/session/{sid}", "#mosaic-viewer[data-ready]")
            for width in WIDTHS:  # the mosaic's legend leaves its zoom buttons free
                page.set_viewport_size({"width": width, "height": 800})
                page.wait_for_timeout(200)
                covered = page.evaluate(COVERED_BUTTONS)
                if covered:
                    wrong.append(f"the mosaic legend covers {covered} at {width} px")
            # a structure with the long names and places real ones have
            httpx.post(
                f"{live_server.url}/api/structures",
                json={
                    "name": "Interstate 5 Columbia River Bridge, northbound",
                    "owner_id": "WA-0005-0000-1234-5678",
                    "location": "Vancouver WA to Portland OR, span 3 over the shipping channel",
                },
            ).raise_for_status()
            wrong += widths_over(
                page, f"{live_server.url}/#/structures", "#structures tr[data-structure]"
            )
        finally:
            browser.close()
    assert wrong == []
    assert errors == []
