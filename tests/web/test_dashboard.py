"""The dashboard in Debian's headless chromium against the real server and simulator: live
video and telemetry, session review with the mosaic viewer and a review that survives a
reload, downloads, 3D view (driving: :mod:`tests.web.test_dashboard_driving`).
Screenshots of each page go to the test's output folder."""

from __future__ import annotations

import uuid
from pathlib import Path

import httpx
import pytest

from robot_link.protocol import MessageType
from tests.conftest import LiveServer
from tests.server.helpers import msg, robot_ws, start
from tests.web.browser import (
    CHROMIUM,
    open_dashboard,
    shot,
    sim,
    wait_js,
    wait_until,
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


# the review's storage (defects, reviews, reports) is tested on both databases over REST
@pytest.mark.one_database
def test_inspection_live_then_review_with_mosaic_viewer_and_3d(
    live_server: LiveServer, tmp_path: Path
) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    foreign: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_dashboard(pw, live_server.url, errors, foreign)
        page.wait_for_selector("#link-state.ok", timeout=15000)
        robot = sim(live_server, "--exit-when-done", "--lanes", "1", "--time-scale", "4")
        try:
            wait_js(
                page,
                "Number(document.querySelector('#camera').dataset.frames || 0) >= 2",
                timeout=120000,
            )
            page.wait_for_selector("#telemetry dt", timeout=20000)
            assert "battery" in page.inner_text("#telemetry")
            shot(page, "drive-route")
        finally:
            _, err = robot.communicate(timeout=120)
        assert robot.returncode == 0, err[-2000:]
        page.goto(live_server.url + "/#/sessions")
        wait_js(
            page,
            "document.querySelector('#sessions tbody')?.textContent.includes('detect ✓')",
            timeout=120000,
        )
        row_text = page.inner_text("#sessions tbody tr:first-child")
        assert "test-robot" in row_text and " s" in row_text  # the robot's name, the duration
        structure = page.inner_text("#sessions tbody tr:first-child td:first-child")
        page.fill("#session-search", "no such girder")
        wait_js(page, "document.querySelectorAll('#sessions tbody tr').length === 0")
        page.fill("#session-search", structure.split()[-1].upper())
        wait_js(page, "document.querySelectorAll('#sessions tbody tr').length === 1")
        shot(page, "sessions")
        page.click("#sessions tbody tr:first-child")
        page.wait_for_selector("#defects tr[data-defect]", timeout=20000)
        # OpenSeadragon over the tile pyramid
        page.wait_for_selector("#mosaic-viewer[data-ready]", timeout=20000)
        assert (
            page.locator(".defect-box").count() == page.locator("#defects tr[data-defect]").count()
        )
        assert "crack" in page.inner_text("#defects") or "corrosion" in page.inner_text("#defects")
        wait_js(
            page, "document.querySelector('#session-coverage').textContent.includes('m² imaged')"
        )
        # which data the results were made from: all of it
        cover = page.inner_text("#results-cover")
        assert "frames" in cover and "everything the session holds" in cover, cover
        # defects carry their session number (#1, #2, ...) in the table and on the mosaic
        numbers = page.locator("#defects tr[data-defect] td:first-child").all_inner_texts()
        assert sorted(numbers, key=lambda n: int(n[1:])) == [
            f"#{i}" for i in range(1, len(numbers) + 1)
        ]
        assert sorted(page.locator(".defect-box .defect-number").all_inner_texts(), key=int) == [
            n[1:] for n in sorted(numbers, key=lambda n: int(n[1:]))
        ]
        # keyboard review: next defect, confirm, condition state 3; then a comment; the
        # detail panel follows each change
        page.keyboard.press("j")
        defect_id = page.get_attribute("#defects tr.selected", "data-defect")
        page.keyboard.press("x")
        wait_js(
            page,
            "document.querySelector('#defect-detail .review-state')?.textContent === 'rejected'",
        )
        page.keyboard.press("c")
        wait_js(
            page,
            "document.querySelector('#defect-detail .review-state').textContent === 'confirmed'",
        )
        page.keyboard.press("3")
        wait_js(page, "document.querySelector('#defect-detail .review-cs').textContent === 'CS3'")
        row = page.locator(f"#defects tr[data-defect='{defect_id}']")
        row.locator("input[name=comment]").fill("check weld toe")
        row.locator("input[name=comment]").press("Tab")
        page.wait_for_selector(f"#defects tr[data-defect='{defect_id}'] input.saved", timeout=10000)
        page.wait_for_selector(
            f"#defects tr[data-defect='{defect_id}'] select[name=condition_state].saved",
            timeout=10000,
        )
        wait_js(
            page,
            "document.querySelector('#defect-detail .review-comment').textContent === 'check weld toe'",
        )
        sid = page.inner_text("#session-detail h3").split(" — ")[-1]
        stored = httpx.get(f"{live_server.url}/api/sessions/{sid}/defects/{defect_id}").json()
        assert (stored["review_status"], stored["condition_state"], stored["comment"]) == (
            "confirmed",
            "CS3",
            "check weld toe",
        )
        # the review survives a reload of the page
        page.reload()
        page.wait_for_selector(f"#defects tr[data-defect='{defect_id}']", timeout=20000)
        row = page.locator(f"#defects tr[data-defect='{defect_id}']")
        assert row.locator("select[name=review_status]").input_value() == "confirmed"
        assert row.locator("select[name=condition_state]").input_value() == "CS3"
        assert row.locator("input[name=comment]").input_value() == "check weld toe"
        # filters and sorting
        page.select_option("#filter-review", "confirmed")
        assert page.locator("#defects tr[data-defect]").count() == 1
        page.select_option("#filter-review", "")
        page.click("#defects th:has-text('length')")
        page.click("#defects th:has-text('length')")  # descending
        lengths = [
            float(t)
            for t in page.locator("#defects tr[data-defect] td:nth-child(3)").all_inner_texts()
            if t != "–"
        ]
        assert lengths == sorted(lengths, reverse=True)
        # one format per quantity: lengths to 0.1 mm, widths to 0.01 mm, positions to 1 mm
        for column, decimals in ((3, 1), (4, 2), (6, 3), (7, 3)):
            cells = page.locator(
                f"#defects tr[data-defect] td:nth-child({column})"
            ).all_inner_texts()
            assert all(c == "–" or len(c.split(".")[1]) == decimals for c in cells), (column, cells)
        # the network's confidence in each crack: a column to sort by, a filter for the doubtful
        listed = httpx.get(f"{live_server.url}/api/sessions/{sid}/defects?source=mosaic").json()
        confidences = [d["confidence"] for d in listed["data"] if d["confidence"] is not None]
        assert confidences and all(0 < c < 1 for c in confidences)
        page.click("#defects th:has-text('confidence')")
        shown = [
            float(t)
            for t in page.locator("#defects tr[data-defect] td:nth-child(8)").all_inner_texts()
            if t != "–"
        ]
        assert shown == sorted(shown) and len(shown) == len(confidences)
        page.select_option("#filter-confidence", "0.5")
        doubtful = sum(c < 0.5 for c in confidences)
        assert page.locator("#defects tr[data-defect]").count() == doubtful
        page.select_option("#filter-confidence", "")
        # filters hide the boxes on the mosaic too
        page.select_option("#filter-class", "corrosion")
        rows = page.locator("#defects tr[data-defect]").count()
        assert page.locator(".defect-box:visible").count() == rows
        page.select_option("#filter-class", "")
        # the viewer's legend, scale bar and the cursor's place on the structure
        assert "corrosion" in page.inner_text(".mosaic-legend")
        page.locator("#mosaic-viewer").scroll_into_view_if_needed()
        viewer = page.locator("#mosaic-viewer").bounding_box()
        cx, cy = viewer["x"] + viewer["width"] / 2, viewer["y"] + viewer["height"] / 2
        page.mouse.move(cx, cy)
        wait_js(
            page,
            "/^x [0-9.]+ m, y [0-9.]+ m$/.test(document.querySelector('#cursor-position').textContent)",
        )
        bar_px = page.locator("#scale-bar .bar").bounding_box()["width"]
        bar_text = page.inner_text("#scale-bar span")
        value, unit = bar_text.split()
        bar_mm = float(value) * {"mm": 1, "cm": 10, "m": 1000}[unit]
        # measuring: two clicks 200 screen pixels apart read as the scale bar says
        page.click("#tool-measure")
        page.mouse.click(cx - 100, cy)
        page.mouse.click(cx + 100, cy)
        wait_js(page, "document.querySelector('#tool-readout').dataset.mm > 0")
        measured = float(page.get_attribute("#tool-readout", "data-mm"))
        assert measured == pytest.approx(200 * bar_mm / bar_px, rel=0.03)
        assert "mm" in page.inner_text("#tool-readout")
        page.click("#tool-measure")  # off
        # a missed defect drawn by hand: stored, numbered after the others, listed
        count = page.locator("#defects tr[data-defect]").count()
        page.click("#tool-draw")
        page.select_option("#draw-class", "corrosion")
        page.mouse.click(cx - 30, cy - 20)
        page.mouse.click(cx + 30, cy + 20)
        wait_js(
            page, f"document.querySelectorAll('#defects tr[data-defect]').length === {count + 1}"
        )
        assert "drawn" in page.inner_text("#tool-readout")
        new_row = page.locator("#defects tr.selected")
        assert new_row.locator("td:first-child").inner_text() == f"#{count + 1}"
        assert "corrosion" in new_row.inner_text()
        shot(page, "session-review")
        # from a report's defect link to the frames it was seen in: the link opens the page on
        # that defect, one click on the strip shows a frame with the moment's telemetry
        report = httpx.get(f"{live_server.url}/api/sessions/{sid}/report.json").json()
        link = report["defects"][1]["dashboard_url"]
        assert link.endswith(f"/#/session/{sid}/defect/2")
        page.goto("about:blank")
        page.goto(link)
        page.wait_for_selector("#defects tr.selected", timeout=20000)
        assert page.inner_text("#defects tr.selected td:first-child") == "#2"
        page.wait_for_selector("#replay .replay-thumb", timeout=20000)
        thumbs = page.locator("#replay .replay-thumb")
        assert "Seen in" in page.inner_text("#replay h4")
        thumbs.nth(thumbs.count() - 1).click()
        last = page.get_attribute(".replay-thumb.selected", "data-seq")
        wait_js(page, f"document.querySelector('#replay').dataset.shown === '{last}'")
        wait_js(page, "document.querySelector('.replay-caption').textContent.includes('battery')")
        caption = page.inner_text(".replay-caption")
        assert f"frame {last}" in caption and "heading" in caption
        # the session timeline scrubs through every frame, the defect's marked
        page.focus("#replay input[type=range]")
        page.keyboard.press("End")
        frames = httpx.get(
            f"{live_server.url}/api/sessions/{sid}/frames", params={"limit": 1000}
        ).json()
        final = str(frames["data"][-1]["seq"])
        wait_js(page, f"document.querySelector('#replay').dataset.shown === '{final}'")
        wait_js(
            page,
            f"document.querySelector('.replay-caption').textContent.startsWith('frame {final}')",
        )
        wait_js(page, "document.querySelector('.replay-frame').naturalWidth > 0")
        shot(page, "session-replay")
        # downloads from the page
        with page.expect_download(timeout=120000) as dl:
            page.click("#exports button[data-export='report.pdf']")
        dl.value.save_as(tmp_path / "report.pdf")
        assert (tmp_path / "report.pdf").read_bytes().startswith(b"%PDF")
        with page.expect_download(timeout=120000) as dl:
            page.click("#exports button[data-export='defects.csv']")
        dl.value.save_as(tmp_path / "defects.csv")
        assert "check weld toe" in (tmp_path / "defects.csv").read_text(encoding="utf-8-sig")
        page_errors = list(errors)  # the 3D view's own WebGL console is not the dashboard's
        # the 3D map, proxied from viser, embedded in the session page: its own scene, which
        # a robot going live meanwhile does not take over
        live_robot = robot_ws(live_server)
        live_sid = uuid.uuid4()
        live_robot.send(start(live_sid))
        live_robot.send(
            msg(live_sid, 2, MessageType.TELEMETRY, {"pose": {"x": 0.2, "y": 0.1, "yaw": 0.0}})
        )
        page.click("#show-3d")
        page.wait_for_selector("#view3d", timeout=20000)
        frame = page.frame_locator("#view3d")
        frame.locator("#root").wait_for(timeout=30000)
        frame.get_by_text("Click a defect marker to see it.").wait_for(timeout=30000)
        frame.get_by_text("Simulated plate girder").first.wait_for(timeout=30000)
        scenes = live_server.app.state.steelscan.scenes
        assert scenes.get(sid).session_id == sid
        assert scenes.live.session_id == str(live_sid)
        page.wait_for_timeout(1500)
        assert frame.get_by_text("Live:").count() == 0
        live_robot.close()
        # linked views: selecting a defect on the page flies the 3D view to it, and a
        # marker clicked in the 3D view selects its defect on the page
        page.keyboard.press("k")
        chosen = int(page.get_attribute("#defects tr.selected", "data-defect"))
        wait_until(lambda: scenes.get(sid).focused == chosen, 10, "the 3D view to fly there")
        other = next(
            int(r)
            for r in page.locator("#defects tr[data-defect]").evaluate_all(
                "rows => rows.map(r => r.dataset.defect)"
            )
            if int(r) != chosen and int(r) in scenes.get(sid).markers
        )
        scenes.get(sid).on_select(other)  # what viser calls when its marker is clicked
        wait_js(
            page, f"document.querySelector('#defects tr.selected')?.dataset.defect === '{other}'"
        )
        shot(page, "session-3d")
        browser.close()
    assert page_errors == []
    assert foreign == []
