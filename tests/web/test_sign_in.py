"""Signing in and out of the dashboard in Debian's headless chromium against the real server:
a sign-in page with nothing else on it, wrong passwords, the throttle's wait said in words,
and a sign-out that ends the token."""

from __future__ import annotations

import httpx
import pytest

from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import add_user
from tests.web.browser import CHROMIUM, launch, shot, wait_js

pytestmark = [
    pytest.mark.slow,
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed"),
]


def test_sign_in_throttle_and_sign_out(live_server: LiveServer) -> None:
    from playwright.sync_api import sync_playwright

    add_user(live_server, "otto", Role.operator)
    errors: list[str] = []
    with sync_playwright() as pw:
        browser = launch(pw)
        page = browser.new_page()
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.goto(live_server.url + "/")
        page.wait_for_selector("#login:not([hidden])", timeout=15000)
        # nothing but the form: no nav, no link state, no e-stop that cannot work yet
        for hidden in ("nav", "#link-state", "#estop"):
            assert not page.is_visible(hidden), hidden
        assert page.evaluate("document.activeElement.name") == "username"
        shot(page, "sign-in")
        assert errors == []  # the page asks for a sign-in without a 401 from the API first
        page.fill("input[name=username]", "otto")
        page.fill("input[name=password]", "wrong password")
        page.click("#login button")
        wait_js(page, "document.querySelector('#login-error').textContent.includes('wrong')")
        # the throttle: after repeated wrong passwords the page says to wait, and how long
        for _ in range(6):  # each answered before the next: a slow hash never lets them overlap
            with page.expect_response(lambda r: r.url.endswith("/api/auth/token")):
                page.click("#login button")
        wait_js(page, "document.querySelector('#login-error').textContent.includes('wait')")
        message = page.inner_text("#login-error")
        assert "too many wrong passwords" in message and " s (until " in message
        errors.clear()  # refused sign-ins are 401 and 429 by design
        live_server.app.state.steelscan.logins.succeeded("127.0.0.1", "otto")  # the wait is over
        page.fill("input[name=password]", "correct horse")
        page.click("#login button")
        wait_js(page, "document.querySelector('#who').textContent.includes('otto (operator)')")
        page.wait_for_selector("#link-state.ok", timeout=15000)
        assert page.is_visible("#estop") and page.is_visible("#sign-out")
        token = page.evaluate("sessionStorage.getItem('steelscan-token')")
        headers = {"Authorization": f"Bearer {token}"}
        assert httpx.get(f"{live_server.url}/api/auth/me", headers=headers).status_code == 200
        page.click("#sign-out")
        page.wait_for_selector("#login:not([hidden])", timeout=15000)
        assert not page.is_visible("#estop")
        assert page.evaluate("sessionStorage.getItem('steelscan-token')") is None
        assert httpx.get(f"{live_server.url}/api/auth/me", headers=headers).status_code == 401
        browser.close()
    assert [e for e in errors if "401" not in e] == []
