"""What the browser tests share: Debian's chromium, screenshots, waiting on the page from
outside it (the dashboard's content security policy forbids in-page evaluation of
strings), recording the page's errors, and the simulated robot as a subprocess."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

import httpx

from tests.conftest import LiveServer

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SHOTS = Path(__file__).resolve().parent.parent.parent / "test-output" / "screenshots"


def shot(page, name: str) -> None:  # type: ignore[no-untyped-def]
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def watch_errors(page, errors: list[str], foreign: list[str]) -> None:  # type: ignore[no-untyped-def]
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("response", lambda r: errors.append(f"{r.status} {r.url}") if r.status >= 400 else None)
    page.on(
        "request",
        lambda r: (
            foreign.append(r.url)
            if urlparse(r.url).hostname not in ("127.0.0.1", None)
            and not r.url.startswith(("data:", "blob:"))
            else None
        ),
    )


def wait_js(page, expression: str, timeout: float = 30000) -> None:  # type: ignore[no-untyped-def]
    """Wait until a JavaScript expression is true on the page, evaluated from outside it (the
    dashboard's content security policy forbids the string evaluation wait_for_function
    uses inside the page)."""
    deadline = time.monotonic() + timeout / 1000
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {expression}")
        page.wait_for_timeout(100)


def launch(pw):  # type: ignore[no-untyped-def]
    """Debian's chromium, headless (Playwright's own browser download is not used)."""
    return pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)


def open_dashboard(pw, url: str, errors: list[str], foreign: list[str]):  # type: ignore[no-untyped-def]
    """Debian's chromium on the dashboard, recording errors and requests to other hosts."""
    browser = launch(pw)
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    watch_errors(page, errors, foreign)
    page.goto(url + "/")
    return browser, page


def sim(live_server: LiveServer, *args: str, log: Path | None = None) -> subprocess.Popen[str]:
    """``steelscan sim`` as a subprocess; a long-running one logs to a file (a pipe nobody
    reads would fill up and stall it)."""
    out = log.open("w") if log is not None else subprocess.PIPE
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "server.cli",
            "sim",
            "--server",
            live_server.url,
            f"--token={live_server.token}",
            *args,
        ],
        stdout=out,
        stderr=subprocess.STDOUT if log is not None else subprocess.PIPE,
        text=True,
    )


def latest_telemetry(url: str, sid: str) -> dict:
    count = httpx.get(f"{url}/api/sessions/{sid}/telemetry", params={"limit": 1}).json()["count"]
    return httpx.get(
        f"{url}/api/sessions/{sid}/telemetry", params={"skip": max(0, count - 1), "limit": 1}
    ).json()["data"][0]["data"]


def _samples_around(url: str, sid: str, t: float) -> list[dict]:
    return httpx.get(
        f"{url}/api/sessions/{sid}/telemetry", params={"since": t - 5.0, "limit": 5000}
    ).json()["data"]


def stood_still(url: str, sid: str, t: float) -> float | None:
    """When (the robot's clock) the robot first reported standing still at or after ``t``;
    None before it has."""
    samples = [s for s in _samples_around(url, sid, t) if s["timestamp"] >= t]
    return next((s["timestamp"] for s in samples if s["data"]["drive"]["linear_mps"] == 0.0), None)


def drove_on(url: str, sid: str, t: float) -> tuple[float, float]:
    """How far (m) the robot drove from its last report before ``t`` (robot clock) to its
    first report standing still after it, and the speed (m/s) it drove at before ``t``."""
    samples = _samples_around(url, sid, t)
    before = [s for s in samples if s["timestamp"] < t][-1]["data"]
    still = next(
        s["data"]
        for s in samples
        if s["timestamp"] >= t and s["data"]["drive"]["linear_mps"] == 0.0
    )
    moved = math.hypot(
        still["pose"]["x"] - before["pose"]["x"], still["pose"]["y"] - before["pose"]["y"]
    )
    return float(moved), float(before["drive"]["linear_mps"])


def wait_until(predicate, timeout_s: float, what: str) -> float:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout_s, f"timed out waiting for {what}"
        time.sleep(0.05)
    return time.monotonic() - t0
