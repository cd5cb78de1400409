"""The structure page in Debian's headless chromium, on the processed inspection: a
structure created, an element drawn on the session's mosaic, the session attached; with an
earlier visit on record, the timeline of both, the element condition table, the changes since
the earlier visit, and a grown crack compared side by side, in the swipe view and over time;
the element deleted again."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer
from tests.server.earlier_visits import add_earlier_visit, forget_session
from tests.web.browser import CHROMIUM, open_dashboard, shot, wait_js

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.one_database,  # the storage behind it is tested on both over REST
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


def test_structure_page_elements_timeline_changes_and_swipe(
    inspected: tuple[LiveServer, str],
) -> None:
    from playwright.sync_api import sync_playwright

    live, sid = inspected
    api = f"{live.url}/api"
    name = f"Bridge {sid[:8]} page"
    errors: list[str] = []
    foreign: list[str] = []
    earlier = None
    with sync_playwright() as pw:
        browser, page = open_dashboard(pw, live.url, errors, foreign)
        try:
            page.goto(f"{live.url}/#/structures")
            page.wait_for_selector("#new-structure")
            page.fill("#new-structure input[name=name]", name)
            page.fill("#new-structure input[name=owner_id]", "NBI 7")
            page.click("#new-structure button[type=submit]")
            page.wait_for_selector("#structure-name")
            assert name in page.inner_text("#structure-name")
            st = int(page.url.split("#/structure/")[1].split("/")[0])
            # the processed session becomes the structure's first visit
            page.wait_for_selector(f"#attach-session option[value='{sid}']", state="attached")
            page.select_option("#attach-session", sid)
            page.click("#attach")
            page.wait_for_selector(f"#timeline .visit[data-session='{sid}']")
            # an element drawn on its mosaic: a box, the element's number, its length prefilled
            page.wait_for_selector("#element-viewer[data-ready]", timeout=20000)
            viewer = page.locator("#element-viewer").bounding_box()
            cx, cy = viewer["x"] + viewer["width"] / 2, viewer["y"] + viewer["height"] / 2
            page.click("#draw-element")
            page.mouse.click(cx - 200, cy - 60)
            page.mouse.click(cx + 200, cy + 60)
            page.wait_for_selector("#element-form:not([hidden])")
            page.select_option("#element-number", "107")
            assert float(page.input_value("#element-quantity")) > 0
            page.fill("#element-name", "girder G3")
            page.click("#add-element")
            page.wait_for_selector("#elements tr[data-element]")
            assert "girder G3" in page.inner_text("#elements")
            page.wait_for_selector("#element-viewer .element-box[data-element]")
            [element] = httpx.get(f"{api}/structures/{st}/elements").json()
            assert element["number"] == 107 and element["quantity"] == pytest.approx(
                max(element["box"][2] - element["box"][0], element["box"][3] - element["box"][1]),
                rel=1e-3,
            )

            # an earlier visit on record: two visits, the latest compared with it
            earlier = add_earlier_visit(live, sid, st)
            page.goto(f"{live.url}/#/structure/{st}")
            wait_js(page, "document.querySelectorAll('#timeline .visit').length === 2")
            dates = page.locator("#timeline .visit b").all_inner_texts()
            assert (
                dates == [earlier.started_at.date().isoformat(), dates[1]] and dates[1] > dates[0]
            )
            page.wait_for_selector("#condition tr[data-element]", timeout=30000)
            assert "girder G3" in page.inner_text("#condition")
            assert "mosaics aligned" in page.inner_text("#registration")
            page.click("#changes tr[data-status=grown]")
            page.wait_for_selector("#defect-compare[data-ready]")
            wait_js(
                page,
                "[...document.querySelectorAll('#defect-compare figure img')]"
                ".filter((i) => i.complete && i.naturalWidth > 0).length === 2",
            )
            page.fill("#swipe-slider", "20")
            wait_js(page, "document.querySelector('.swipe-top').style.clipPath.includes('80%')")
            page.wait_for_selector("#history-chart", timeout=30000)
            assert page.locator("#history-chart circle").count() == 2
            assert "grown" in page.inner_text(".history-table")
            shot(page, "structure")
            # an element deleted goes from the table and the mosaic
            page.click("#elements tr[data-element] button.danger")
            wait_js(page, "!document.querySelector('#elements tr[data-element]')")
            wait_js(page, "!document.querySelector('#element-viewer .element-box[data-element]')")
            assert httpx.get(f"{api}/structures/{st}/elements").json() == []
        finally:
            browser.close()
            if earlier is not None:
                forget_session(live, earlier.id)
            httpx.put(f"{api}/sessions/{sid}/structure", json={"structure_id": None})
    assert errors == [] and foreign == []
