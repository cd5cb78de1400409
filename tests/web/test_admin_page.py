"""Administration from the dashboard in Debian's headless chromium against the real server:
register a robot (its token shown once, and it connects), add the first account (sign-in
starts), import an MCAP log into a new session and run a processing stage again."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import httpx
import pytest

from robot_link.protocol import MessageType, decode_message
from server.config import Settings
from tests.conftest import LiveServer
from tests.server.helpers import frame, msg, robot_ws, start, wait_job
from tests.web.browser import CHROMIUM, launch, shot, wait_js, watch_errors

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


@pytest.fixture
def settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"auto_process": False, "view3d": False})


def exported_session(server: LiveServer, path: Path) -> None:
    """A short session recorded over the robot link and exported as MCAP to ``path``."""
    sid = uuid.uuid4()
    with robot_ws(server) as ws:
        for m in (
            start(sid),
            frame(sid, 2),
            frame(sid, 3),
            msg(sid, 4, MessageType.SESSION_END, {}),
        ):
            ws.send(m)
            decode_message(ws.recv(timeout=10))
    url = f"{server.url}/api/sessions/{sid}/export.mcap"
    wait_job(server.url, httpx.get(url).json()["id"])
    path.write_bytes(httpx.get(url).raise_for_status().content)


def test_robots_accounts_import_and_jobs(live_server: LiveServer, tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    errors: list[str] = []
    exported_session(live_server, tmp_path / "bridge.mcap")
    with sync_playwright() as pw:
        browser = launch(pw)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        watch_errors(page, errors, [])

        def accept(dialog) -> None:  # type: ignore[no-untyped-def]
            dialog.accept()

        page.on("dialog", accept)
        page.goto(live_server.url + "/#/admin")
        page.wait_for_selector("#robots tr[data-robot='test-robot']", timeout=15000)
        assert page.is_visible("#nav-admin")
        # a robot registered here connects with the token shown once
        page.fill("#add-robot input[name=name]", "crawler-9")
        page.click("#add-robot button")
        page.wait_for_selector("#new-robot-token", timeout=10000)
        token = page.inner_text("#new-robot-token")
        assert page.is_visible("#robots tr[data-robot='crawler-9']")
        with robot_ws(live_server, token) as ws:
            ws.send(start(uuid.uuid4()))
            decode_message(ws.recv(timeout=10))
        shot(page, "admin")
        # an MCAP log becomes a new session; a stage runs again from the session page
        page.goto(live_server.url + "/#/sessions")
        page.set_input_files("#import-mcap", str(tmp_path / "bridge.mcap"))
        page.wait_for_selector("#jobs-bar button[data-job=export]", timeout=20000)
        assert "2 frames" in page.inner_text("#session-detail")
        page.click("#jobs-bar button[data-job=export]")
        wait_js(
            page,
            "document.querySelector('#job-status')?.textContent === 'MCAP export: done'",
            60000,
        )
        sid = page.inner_text("#session-detail h3").split(" — ")[-1]
        jobs = httpx.get(f"{live_server.url}/api/sessions/{sid}/jobs").json()
        assert [j["state"] for j in jobs if j["kind"] == "export"][-1] == "done"
        # a finished stage asks before it runs again: declined, nothing is queued
        asked: list[str] = []

        def decline(dialog) -> None:  # type: ignore[no-untyped-def]
            asked.append(dialog.message)
            dialog.dismiss()

        page.wait_for_selector("#jobs-bar button[data-job=export]", timeout=20000)
        page.remove_listener("dialog", accept)
        page.once("dialog", decline)
        page.click("#jobs-bar button[data-job=export]")
        page.wait_for_timeout(500)
        assert asked and "again" in asked[0] and "replaced" in asked[0]
        again = httpx.get(f"{live_server.url}/api/sessions/{sid}/jobs").json()
        assert len([j for j in again if j["kind"] == "export"]) == len(
            [j for j in jobs if j["kind"] == "export"]
        )
        # the first account switches sign-in on: the page asks for it
        page.goto(live_server.url + "/#/admin")
        page.wait_for_selector("#add-user", timeout=10000)
        page.fill("#add-user input[name=name]", "ada")
        page.fill("#add-user input[name=password]", "correct horse")
        page.select_option("#add-user select[name=role]", "admin")
        page.click("#add-user button")
        page.wait_for_selector("#login:not([hidden])", timeout=15000)
        errors.clear()  # the 401s that end the open station are expected
        page.fill("input[name=username]", "ada")
        page.fill("input[name=password]", "correct horse")
        page.click("#login button")
        # signed in (the form hides) before the next page asks for anything; a request the
        # signed-out page sent before that may still come back 401
        page.wait_for_selector("#login", state="hidden", timeout=15000)
        page.wait_for_load_state("networkidle")
        errors.clear()
        page.goto(live_server.url + "/#/admin")
        page.wait_for_selector("#users tr[data-user='ada']", timeout=15000)
        assert page.input_value("#users tr[data-user='ada'] select") == "admin"
        browser.close()
    time.sleep(0.1)
    assert errors == []
