"""The session page's Jobs bar in Debian's headless chromium against a station whose jobs go
to a Celery queue (real Redis) with no worker yet: a job stays queued, the page follows it,
including after a reload, and cancels it."""

from __future__ import annotations

import uuid
from pathlib import Path

import httpx
import pytest

from robot_link.protocol import MessageType, decode_message
from server.config import Settings
from server.loopback import BackgroundServer, free_port
from tests.conftest import LiveServer, make_token
from tests.server.helpers import frame, msg, robot_ws, start
from tests.web.browser import CHROMIUM, launch, wait_js, watch_errors

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


def test_a_queued_job_is_followed_and_cancelled_from_the_session_page(
    tmp_path: Path,
    redis_server,  # type: ignore[no-untyped-def]
) -> None:
    from playwright.sync_api import sync_playwright

    settings = Settings(
        data_dir=tmp_path / "data",
        job_backend="celery",
        broker_url=redis_server.url,
        auto_process=False,
        view3d=False,
        live_map=False,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    live = LiveServer(server.url, settings, token)
    try:
        sid = uuid.uuid4()
        with robot_ws(live) as ws:
            for m in (start(sid), frame(sid, 2), msg(sid, 3, MessageType.SESSION_END, {})):
                ws.send(m)
                decode_message(ws.recv(timeout=10))
        errors: list[str] = []
        with sync_playwright() as pw:
            browser = launch(pw)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            watch_errors(page, errors, [])
            page.goto(f"{server.url}/#/session/{sid}")
            page.wait_for_selector("#jobs-bar button[data-job=stitch]", timeout=20000)
            assert not page.is_visible("#job-cancel")
            page.click("#jobs-bar button[data-job=stitch]")
            wait_js(
                page,
                "document.querySelector('#job-status')?.textContent.startsWith('mosaic: queued')",
                15000,
            )
            assert page.inner_text("#job-cancel") == "Cancel mosaic"
            # a job under way when the page opens is followed too
            page.reload()
            page.wait_for_selector("#job-cancel:not([hidden])", timeout=20000)
            page.click("#job-cancel")
            wait_js(
                page,
                "document.querySelector('#job-status')?.textContent.startsWith('mosaic: cancelled')",
                15000,
            )
            assert "cancelled by" in page.inner_text("#job-status")
            assert not page.is_visible("#job-cancel")
            browser.close()
        jobs = httpx.get(f"{server.url}/api/sessions/{sid}/jobs").json()
        assert [(j["kind"], j["state"]) for j in jobs] == [("stitch", "cancelled")]
        assert errors == []
    finally:
        server.stop()
