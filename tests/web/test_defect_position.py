"""A defect's position on the session page of the processed inspection: the table's x, y
and the selected defect's panel give the REST record's world_x_m, world_y_m and say what
that point is (the corner of the defect's box nearest the origin), then the box."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer
from tests.web.browser import CHROMIUM, open_dashboard, wait_js

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.one_database,  # the page only reads what REST gives
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]

CORNER = "the corner of the defect's box nearest the structure's origin"


def test_the_table_and_panel_name_the_box_corner_they_show(
    inspected: tuple[LiveServer, str],
) -> None:
    from playwright.sync_api import sync_playwright

    live, sid = inspected
    defects = httpx.get(f"{live.url}/api/sessions/{sid}/defects", params={"limit": 5000}).json()
    d = next(x for x in defects["data"] if x["source"] == "mosaic" and x["world_x_m"] is not None)
    x0, y0 = d["world_x_m"], d["world_y_m"]
    x1, y1 = x0 + d["world_w_m"], y0 + d["world_h_m"]
    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_dashboard(pw, live.url, errors, [])
        try:
            page.goto(f"{live.url}/#/session/{sid}")
            row = page.locator(f"#defects tr[data-defect='{d['id']}']")
            row.wait_for(timeout=20000)
            cells = row.locator("td").all_inner_texts()
            assert f"{x0:.3f}" in cells and f"{y0:.3f}" in cells
            assert CORNER in page.inner_text("#defects-position")
            titles = page.locator("#defects th[title]").evaluate_all(
                "ths => ths.map(th => [th.textContent, th.title])"
            )
            assert [t for _, t in titles] == [f"x of {CORNER}", f"y of {CORNER}"]
            assert [h[:5] for h, _ in titles] == ["x (m)", "y (m)"]
            row.locator("td").first.click()
            wait_js(
                page, f"document.querySelector('#defect-detail')?.dataset.defect === '{d['id']}'"
            )
            assert page.inner_text("#defect-detail .defect-position") == (
                f"x {x0:.3f} m, y {y0:.3f} m ({CORNER})"
            )
            assert page.inner_text("#defect-detail .defect-box-m") == (
                f"x {x0:.3f}–{x1:.3f} m, y {y0:.3f}–{y1:.3f} m"
            )
        finally:
            browser.close()
    assert errors == []
