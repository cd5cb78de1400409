"""One robot or one flood cannot exhaust the station's file descriptors: segment files are
opened lazily and only so many at once, a robot holds only so many live sessions, the
station raises its open-file limit, and connections still sending their head give way to
newcomers (real server, real sockets)."""

import os
import resource
import socket
import time
import uuid
from pathlib import Path

import httpx

from server.config import Settings
from server.link.guard import FD_WANTED
from server.loopback import BackgroundServer, free_port
from server.storage.files import SessionFiles
from tests.conftest import LiveServer, make_token
from tests.server.helpers import frame, robot_ws, send_and_reply, session_json, start


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_segment_files_are_opened_lazily_and_only_so_many_at_once(tmp_path: Path) -> None:
    files = SessionFiles(tmp_path, max_open=8)
    stored = []
    for k in range(50):
        stored.append((files.append(f"s{k}", "frames", b"frame %d" % k), b"frame %d" % k))
        assert files.open_files <= 8
    for (rel, offset), data in stored:
        assert files.read(rel, offset, len(data)) == data
    rel, offset = files.append("s0", "frames", b"again")  # opened again, same segment
    assert rel == stored[0][0][0] and offset == len(b"frame 0")


def test_a_robot_holds_only_so_many_live_sessions(live_server: LiveServer) -> None:
    limit = live_server.settings.max_live_sessions_per_robot
    before = _open_fds()
    sids = [uuid.uuid4() for _ in range(120)]
    with robot_ws(live_server) as ws:
        for sid in sids:
            assert send_and_reply(ws, start(sid)).meta["status"] == "stored"
            assert send_and_reply(ws, frame(sid, 2)).meta["status"] == "stored"
    # the station's own process serves this test: its descriptors did not grow per session
    assert _open_fds() - before < 70
    live = httpx.get(f"{live_server.url}/api/sessions", params={"status": "live"}).json()
    assert live["count"] == limit
    assert {s["id"] for s in live["data"]} == {str(s) for s in sids[-limit:]}
    first = session_json(live_server, sids[0])
    assert first["status"] == "ended" and "started session" in first["end_reason"]
    assert first["frames"] == 1  # nothing lost


def test_the_station_raises_its_open_file_limit(live_server: LiveServer) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = FD_WANTED if hard == resource.RLIM_INFINITY else min(FD_WANTED, hard)
    assert soft >= wanted


def test_connections_that_never_finish_their_head_give_way(tmp_path: Path) -> None:
    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=f"sqlite:///{tmp_path / 'data' / 'steelscan.db'}",
        max_connections_per_client=1000,
        max_pending_connections=40,
        request_head_timeout_s=60,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    host, port = server.url.removeprefix("http://").split(":")
    slow = []
    try:
        for k in range(300):  # from twenty addresses, each a partial request line
            sock = socket.socket()
            sock.bind((f"127.0.0.{2 + k % 20}", 0))
            sock.connect((host, int(port)))
            sock.sendall(b"GET /api/health HTTP/1.1\r\nHo")
            slow.append(sock)
        time.sleep(0.5)
        for _ in range(5):
            assert httpx.get(f"{server.url}/api/health", timeout=5).status_code == 200
        with robot_ws(LiveServer(server.url, settings, token), open_timeout=5) as ws:
            sid = uuid.uuid4()
            assert send_and_reply(ws, start(sid)).meta["status"] == "stored"
        closed = 0
        for sock in slow:
            sock.settimeout(0.01)
            try:
                closed += sock.recv(1) == b""
            except (TimeoutError, ConnectionResetError):
                closed += 0
        assert closed >= 300 - 40 - 10  # all but the newest pending ones were let go
    finally:
        for sock in slow:
            sock.close()
        server.stop()
