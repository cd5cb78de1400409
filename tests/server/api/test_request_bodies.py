"""Request bodies on the real server: nobody unauthenticated gets a byte of a body read,
bodies are capped per route and must arrive in time, and an upload streams into the data
directory within its disk reserve."""

import shutil
import socket
import time
from pathlib import Path

import httpx

from server.config import Settings
from server.loopback import BackgroundServer, free_port
from server.storage.models import Role
from tests.conftest import LiveServer
from tests.server.helpers import add_user, login


def _raw_request(url: str, head: str, body: bytes = b"", *, wait_s: float = 10.0) -> bytes:
    """Send a request head (and the start of a body) over a socket; what came back."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=wait_s) as sock:
        sock.sendall(head.encode() + body)
        return _read_all(sock)


def _read_all(sock: socket.socket) -> bytes:
    out = b""
    try:
        while chunk := sock.recv(65536):
            out += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return out


def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()] if folder.exists() else []


def test_an_unauthenticated_upload_is_refused_before_it_is_read(live_server: LiveServer) -> None:
    add_user(live_server, "ana", Role.operator)
    imports = live_server.settings.data_dir / "imports"
    reply = _raw_request(
        live_server.url,
        "POST /api/sessions/import HTTP/1.1\r\nHost: x\r\n"
        "Content-Type: application/octet-stream\r\nContent-Length: 1000000000\r\n\r\n",
        b"\x89MCAP0\r\n" + bytes(60_000),
    )
    assert reply.startswith(b"HTTP/1.1 401"), reply[:200]
    assert _files(imports) == []
    # a JSON route alike: the body of a PATCH by nobody is never parsed
    patch = httpx.patch(f"{live_server.url}/api/sessions/x", json={"notes": "n" * 100})
    assert patch.status_code == 401


def test_bodies_are_capped_per_route(live_server: LiveServer) -> None:
    add_user(live_server, "ana", Role.operator)
    auth = login(live_server, "ana")
    cap = live_server.settings.max_body_bytes
    big = httpx.patch(
        f"{live_server.url}/api/sessions/x", headers=auth, content=b"{" + b" " * cap + b"}"
    )
    assert big.status_code == 413 and str(cap) in big.json()["detail"]
    head = (
        "PATCH /api/sessions/x HTTP/1.1\r\nHost: x\r\nAuthorization: {}\r\n"
        "Transfer-Encoding: chunked\r\nContent-Type: application/json\r\n\r\n"
    ).format(auth["Authorization"])
    chunk = b" " * 65536
    body = b"".join(b"%x\r\n%s\r\n" % (len(chunk), chunk) for _ in range(cap // len(chunk) + 2))
    reply = _raw_request(live_server.url, head, body)  # no declared size: counted as it comes
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]


def test_a_body_that_trickles_is_cut_off(tmp_path: Path) -> None:
    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=f"sqlite:///{tmp_path / 'data' / 'steelscan.db'}",
        body_grace_s=1.0,
        body_idle_s=0.5,
    )
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        host, port = server.url.removeprefix("http://").split(":")
        socks = []
        for _ in range(20):  # twenty slow bodies: each gets 408 and its connection closes
            sock = socket.create_connection((host, int(port)), timeout=10)
            sock.sendall(
                b"PATCH /api/sessions/x HTTP/1.1\r\nHost: x\r\nContent-Type: application/json"
                b"\r\nContent-Length: 100\r\n\r\n{"
            )
            socks.append(sock)
        for sock in socks:
            with sock:
                for _ in range(3):
                    try:
                        sock.sendall(b" ")
                    except OSError:
                        break
                    time.sleep(0.2)
                reply = _read_all(sock)
                assert reply.startswith(b"HTTP/1.1 408"), reply[:200]
        # a body that keeps pace goes through
        ok = httpx.patch(f"{server.url}/api/sessions/x", json={"notes": "fine"})
        assert ok.status_code == 404  # read, parsed, and the session is not there
    finally:
        server.stop()


def test_an_import_streams_within_the_disk_reserve(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    free = shutil.disk_usage(data).free
    # robots may still store (free > reserve), an import may not (it keeps a second reserve)
    settings = Settings(
        data_dir=data,
        database_url=f"sqlite:///{data / 'steelscan.db'}",
        min_free_bytes=int(free * 0.6),
    )
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        up = httpx.post(
            f"{server.url}/api/sessions/import",
            files={"file": ("big.mcap", b"\x89MCAP0\r\n" + bytes(2_000_000))},
        )
        assert up.status_code == 507 and "retry later" in up.json()["detail"], up.text
        assert _files(data / "imports") == []
        raw = httpx.post(  # the file as the body, within the reserve: read, then judged
            f"{server.url}/api/sessions/import",
            content=b"not an mcap",
            headers={"Content-Type": "application/octet-stream", "X-Filename": "raw.mcap"},
        )
        assert raw.status_code in (422, 507), raw.text
    finally:
        server.stop()
