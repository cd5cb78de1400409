"""The station on loopback: in a thread of this process (:class:`BackgroundServer`) or as a
separate ``steelscan serve`` process (:func:`serve_process`); used by the demo, the
benchmarks and the tests."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import uvicorn

from server.config import Settings
from server.logs import uvicorn_log_config
from server.main import create_app


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class BackgroundServer:
    """uvicorn serving the app in a thread, on loopback."""

    def __init__(self, settings: Settings, port: int) -> None:
        config = uvicorn.Config(
            create_app(settings),
            host="127.0.0.1",
            port=port,
            log_level="warning",
            log_config=uvicorn_log_config(),
            **settings.uvicorn_options(),
            lifespan="on",
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)
        scheme = "https" if settings.tls_cert is not None else "http"
        self.url = f"{scheme}://127.0.0.1:{port}"

    def start(self, timeout_s: float = 60) -> None:
        """Start and wait until it accepts requests."""
        self.thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the ground station did not start")
            time.sleep(0.05)

    def stop(self) -> None:
        """Ask uvicorn to exit and wait for it."""
        self.server.should_exit = True
        self.thread.join(timeout=20)


def serve_process(
    data_dir: Path, port: int, *, log: Path | None = None, **env: str
) -> subprocess.Popen[bytes]:
    """``steelscan serve`` as a separate process on loopback (``env``: extra STEELSCAN_*
    settings; ``log``: a file for its output), returned once it answers its health check."""
    out = subprocess.DEVNULL if log is None else log.open("ab")
    try:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "server.cli",
                "serve",
                "--data-dir",
                str(data_dir),
                "--port",
                str(port),
            ],
            stdout=out,
            stderr=subprocess.STDOUT if log is not None else subprocess.DEVNULL,
            env={**os.environ, **env},
        )
    finally:
        if log is not None:
            out.close()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            # 401: up, with accounts
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1).status_code in (
                200,
                401,
            ):
                return proc
        except httpx.HTTPError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the ground station did not start")
