"""``serve`` over TLS: robots connect over wss:// and check the station's certificate."""

from __future__ import annotations

import asyncio
import shutil
import ssl
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from robot_link.client import LinkError, RobotLink
from robot_link.protocol import MessageType
from server.config import Settings
from server.loopback import BackgroundServer, free_port
from tests.conftest import make_token
from tests.media import jpeg

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")


def _self_signed(folder: Path) -> tuple[Path, Path]:
    cert, key = folder / "station.pem", folder / "station.key"
    subprocess.run(
        [
            "openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
            "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
            "-keyout", str(key), "-out", str(cert),
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return cert, key


def test_robots_send_over_wss_to_a_station_they_trust(tmp_path: Path, database_url: str) -> None:
    cert, key = _self_signed(tmp_path)
    settings = Settings(
        database_url=database_url,
        data_dir=tmp_path / "data",
        job_workers=1,
        tls_cert=cert,
        tls_key=key,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        assert server.url.startswith("https://")
        trust = ssl.create_default_context(cafile=str(cert))
        assert httpx.get(f"{server.url}/api/health", verify=trust).status_code == 200

        async def record(ca_file: str | None) -> RobotLink:
            link = RobotLink(server.url, token, ca_file=ca_file, max_backoff_s=0.2)
            await link.start()
            await link.send(MessageType.SESSION_START, {"structure": "over TLS"})
            await link.send(MessageType.FRAME, {"width": 64, "height": 48}, jpeg(64, 48))
            try:
                await link.flush(timeout_s=3 if ca_file is None else 30)
            finally:
                await link.close()
            return link

        link = asyncio.run(record(str(cert)))
        session = httpx.get(f"{server.url}/api/sessions/{link.session_id}", verify=trust)
        assert session.json()["frames"] == 1
        with pytest.raises(LinkError, match="not trusted"):  # an unknown certificate
            asyncio.run(record(None))
        sim = subprocess.run(  # the simulated robot says so and exits, not retries forever
            [
                sys.executable,
                "-m",
                "server.cli",
                "sim",
                "--server",
                server.url,
                "--token",
                token,
                "--exit-when-done",
                "--lanes",
                "1",
                "--time-scale",
                "0",
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert sim.returncode != 0 and "not trusted" in sim.stderr, sim.stderr[-2000:]
        assert "Traceback" not in sim.stderr
    finally:
        server.stop()


def test_a_certificate_needs_its_key() -> None:
    with pytest.raises(ValueError, match="go together"):
        Settings(tls_cert=Path("station.pem"))
