"""The page at / in Debian's headless chromium, against the real server and simulator."""

import shutil
import subprocess
import sys
from urllib.parse import urlparse

import httpx
import pytest

from tests.conftest import LiveServer

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [pytest.mark.browser, pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")]
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def test_live_page_shows_camera_and_telemetry_with_no_errors(live_server: LiveServer, tmp_path) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    foreign: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("request", lambda r: foreign.append(r.url) if urlparse(r.url).hostname not in ("127.0.0.1", None) and not r.url.startswith("data:") else None)
        page.goto(live_server.url + "/")
        page.wait_for_selector("#link-state.ok", timeout=15000)
        sim = subprocess.Popen([sys.executable, "-m", "server.cli", "sim", "--server", live_server.url, "--token", live_server.token,
                                "--exit-when-done", "--lanes", "1", "--time-scale", "4"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            page.wait_for_function("Number(document.querySelector('#camera').dataset.frames || 0) >= 2", timeout=120000)
            page.wait_for_selector("#telemetry dt", timeout=20000)
            assert "battery" in page.inner_text("#telemetry")
            page.wait_for_function("document.querySelectorAll('#sessions tbody tr').length >= 1", timeout=20000)
            page.screenshot(path=str(tmp_path / "dashboard.png"))
        finally:
            out, err = sim.communicate(timeout=120)
        assert sim.returncode == 0, err[-2000:]
        # once processed, a session shows its mosaic and defect table
        page.wait_for_function("document.querySelector('#sessions tbody').textContent.includes('detect: done')", timeout=120000)
        page.click("#sessions tbody tr:first-child")
        page.wait_for_function("document.querySelectorAll('#defects tr').length >= 2", timeout=20000)
        assert "crack" in page.inner_text("#defects") or "corrosion" in page.inner_text("#defects")
        # review a defect in the table: saved at once, and in the report downloaded from the page
        row = page.locator("#defects tr[data-defect]").first
        defect_id = row.get_attribute("data-defect")
        row.locator("select[name=review_status]").select_option("confirmed")
        row.locator("select[name=condition_state]").select_option("CS2")
        row.locator("input[name=comment]").fill("check weld toe")
        row.locator("input[name=comment]").press("Enter")
        row.locator("input[name=comment]").blur()
        page.wait_for_selector(f"#defects tr[data-defect='{defect_id}'] input.saved", timeout=10000)
        sid = page.inner_text("#session-detail h3").split(" — ")[-1]
        stored = httpx.get(f"{live_server.url}/api/sessions/{sid}/defects/{defect_id}").json()
        assert (stored["review_status"], stored["condition_state"], stored["comment"]) == ("confirmed", "CS2", "check weld toe")
        with page.expect_download(timeout=120000) as dl:
            page.click("#exports button[data-export='report.pdf']")
        pdf = tmp_path / "report.pdf"
        dl.value.save_as(pdf)
        assert pdf.read_bytes().startswith(b"%PDF")
        with page.expect_download(timeout=120000) as dl:
            page.click("#exports button[data-export='defects.csv']")
        dl.value.save_as(tmp_path / "defects.csv")
        assert "check weld toe" in (tmp_path / "defects.csv").read_text(encoding="utf-8-sig")
        page_errors = list(errors)  # the 3D view's own WebGL console is not the dashboard's
        # the 3D map, proxied from viser under /viser/, embedded in the session page
        page.click("text=Show 3D map")
        page.wait_for_selector("#view3d", timeout=20000)
        frame = page.frame_locator("#view3d")
        frame.locator("#root").wait_for(timeout=30000)
        # the view's own panel arrives over the proxied websocket, with the session's title
        frame.get_by_text("Click a defect marker to see it.").wait_for(timeout=30000)
        frame.get_by_text("Simulated plate girder").first.wait_for(timeout=30000)
        assert live_server.app.state.steelscan.scene.session_id in page.inner_text("#session-detail h3")
        page.screenshot(path=str(tmp_path / "session-3d.png"), full_page=True)
        browser.close()
    assert page_errors == []
    assert foreign == []


def test_sign_in_when_accounts_exist(live_server: LiveServer) -> None:
    from playwright.sync_api import sync_playwright

    from server.models import Role
    from tests.server.test_auth import add_user

    add_user(live_server, "otto", Role.operator)
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        page = browser.new_page()
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(live_server.url + "/")
        page.wait_for_selector("#login:not([hidden])", timeout=15000)
        page.fill("input[name=username]", "otto")
        page.fill("input[name=password]", "wrong password")
        page.click("#login button")
        page.wait_for_function("document.querySelector('#login-error').textContent.length > 0", timeout=10000)
        page.fill("input[name=password]", "correct horse")
        page.click("#login button")
        page.wait_for_function("document.querySelector('#who').textContent.includes('otto (operator)')", timeout=10000)
        page.wait_for_selector("#link-state.ok", timeout=15000)
        browser.close()
    assert errors == []
