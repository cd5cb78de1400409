"""The session timeline on the processed inspection's page, in chromium: one slider moves
the frame, the coverage map, the mosaic cursor and the plots' cursor together; defects are
ticks at the frame they were first seen in; keys step frame by frame; playback runs; the
plotted telemetry fields are kept with the user's preferences on the station."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer
from tests.web.browser import CHROMIUM, open_dashboard, shot, wait_js

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.one_database,  # the page only reads what REST gives
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]

TL = "document.querySelector('#timeline')"


def _at(page) -> dict:  # type: ignore[no-untyped-def]
    """What each view shows now."""
    return page.evaluate(
        """() => ({
            index: Number(document.querySelector('#timeline').dataset.index),
            seq: Number(document.querySelector('#timeline').dataset.seq),
            frame: Number(document.querySelector('#timeline-frame').dataset.seq),
            cursor: document.querySelector('#mosaic-cursor')?.dataset || null,
            defect: document.querySelector('#defect-detail').dataset.defect || null,
        })"""
    )


def test_one_slider_moves_every_view_together(inspected: tuple[LiveServer, str]) -> None:
    from playwright.sync_api import sync_playwright

    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    tl = httpx.get(f"{api}/timeline").json()
    world = httpx.get(f"{api}/results/mosaic.json").json()
    frames = tl["frames"]
    shown = {
        d["id"] for d in httpx.get(f"{api}/defects", params={"source": "mosaic"}).json()["data"]
    }
    ticked = [d for d in tl["defects"] if d["id"] in shown and d["first_seq"] is not None]
    assert len(ticked) >= 3

    def expect(i: int) -> tuple[float, float]:
        k, (ox, oy) = world["px_per_m"], world["origin_m"]
        fp = frames[i]["footprint"]
        return (
            sum(x - ox for x, _ in fp) / 4 * k,
            sum(y - oy for _, y in fp) / 4 * k,
        )

    errors: list[str] = []
    with sync_playwright() as pw:
        browser, page = open_dashboard(pw, live.url, errors, [])
        try:
            page.goto(f"{live.url}/#/session/{sid}")
            wait_js(page, "document.querySelector('#mosaic-viewer')?.dataset.ready === 'true'")
            wait_js(page, f"{TL}?.dataset.frames === '{len(frames)}'")
            wait_js(page, "document.querySelectorAll('#timeline-plots .plot').length >= 1")
            # one tick a frame where defects were first seen
            frames_ticked = {d["first_seq"] for d in ticked}
            assert page.evaluate(f"{TL}.dataset.ticks") == str(len(frames_ticked))
            on_ticks = page.locator(".timeline-tick").evaluate_all(
                "ts => ts.map(t => t.dataset.defects.split(' ').map(Number))"
            )
            assert sorted(i for ids in on_ticks for i in ids) == sorted(d["id"] for d in ticked)
            # keys step frame by frame; every view follows
            page.locator("#session-detail h3").first.click()
            for key, want in ((".", 1), (".", 2), ("ArrowRight", 3), (",", 2)):
                page.keyboard.press(key)
                wait_js(page, f"{TL}.dataset.index === '{want}'")
                seq = frames[want]["seq"]
                wait_js(page, f"document.querySelector('#timeline-frame').dataset.seq === '{seq}'")
                at = _at(page)
                assert at["seq"] == seq and at["cursor"]["seq"] == str(seq)
                cx, cy = expect(want)
                assert abs(float(at["cursor"]["cx"]) - cx) < 0.2
                assert abs(float(at["cursor"]["cy"]) - cy) < 0.2
                assert page.evaluate(f"{TL}.dataset.robot") == ",".join(
                    _js_number(v) for v in frames[want]["robot"]
                )
            assert f"frame {frames[2]['seq']} (3/{len(frames)})" in page.inner_text(
                "#timeline-readout"
            )
            # a defect's tick: the timeline goes to the frame it was first seen in and the
            # defect is selected; a defect selected in the table moves the timeline there
            d = ticked[-1]
            page.locator(f".timeline-tick[data-defects~='{d['id']}']").click()
            want = next(i for i, m in enumerate(frames) if m["seq"] == d["first_seq"])
            wait_js(page, f"{TL}.dataset.index === '{want}'")
            wait_js(
                page, f"document.querySelector('#defect-detail').dataset.defect === '{d['id']}'"
            )
            other = ticked[0]
            page.locator(f"#defects tr[data-defect='{other['id']}'] td").first.click()
            want = next(i for i, m in enumerate(frames) if m["seq"] == other["first_seq"])
            wait_js(page, f"{TL}.dataset.index === '{want}'")
            assert _at(page)["cursor"]["seq"] == str(other["first_seq"])
            # defects first seen in one frame share a tick: each click selects the next
            together = [
                [d for d in ticked if d["first_seq"] == seq]
                for seq in frames_ticked
                if sum(d["first_seq"] == seq for d in ticked) > 1
            ]
            if together:
                tick = page.locator(f".timeline-tick[data-defects~='{together[0][0]['id']}']")
                chosen = set()
                for _ in together[0]:
                    tick.click()
                    page.wait_for_timeout(150)
                    chosen.add(
                        page.evaluate("document.querySelector('#defect-detail').dataset.defect")
                    )
                assert chosen == {str(d["id"]) for d in together[0]}
            # Enter on a timeline button presses it, even with a defect selected
            page.focus("#timeline-next")
            before = int(page.evaluate(f"{TL}.dataset.index"))
            page.keyboard.press("Enter")
            wait_js(page, f"{TL}.dataset.index === '{min(before + 1, len(frames) - 1)}'")
            # a seek while playing: playback goes on from there
            page.select_option("#timeline-speed", "1")
            page.locator("#timeline-slider").fill("0")
            page.click("#timeline-play")
            wait_js(page, f"{TL}.dataset.playing === 'true'")
            page.locator("#timeline-slider").fill(str(len(frames) - 3))
            page.wait_for_timeout(400)
            assert int(page.evaluate(f"{TL}.dataset.index")) >= len(frames) - 3
            page.click("#timeline-play")
            wait_js(page, f"{TL}.dataset.playing === 'false'")
            # playback at 16×: the moments advance in the session's time and stop at its end
            page.select_option("#timeline-speed", "16")
            page.locator("#timeline-slider").fill("0")
            page.click("#timeline-play")
            wait_js(page, f"{TL}.dataset.playing === 'true'")
            page.wait_for_timeout(1200)
            index = int(page.evaluate(f"{TL}.dataset.index"))
            t = float(page.evaluate(f"{TL}.dataset.t"))
            assert index > 0 and 4.0 < t < 40.0, (index, t)
            page.click("#timeline-play")
            wait_js(page, f"{TL}.dataset.playing === 'false'")
            shot(page, "timeline-1400")
            # pick a field to plot: the plots change, and the choice is kept for this user
            field = "ir_range_m[0]"
            page.click("#timeline-fields summary")
            page.check(f"#timeline-fields input[value='{field}']")
            wait_js(
                page,
                f"document.querySelector('#timeline-plots').dataset.fields.includes('{field}')",
            )
            titles = page.locator("#timeline-plots .u-title").all_inner_texts()
            assert any(field in title and "(m)" in title for title in titles), titles
            prefs = f"{live.url}/api/auth/me/preferences"  # the open station's user
            assert field in httpx.get(prefs).json()["plot_fields"]
            page.reload()
            wait_js(
                page,
                f"document.querySelector('#timeline-plots')?.dataset.fields?.includes('{field}')",
            )
        finally:
            browser.close()
            httpx.patch(f"{live.url}/api/auth/me/preferences", json={"plot_fields": None})
    assert errors == []


def _js_number(v: float) -> str:
    """A number as JavaScript writes it."""
    return str(int(v)) if float(v).is_integer() else repr(float(v))
