"""No file outside what a route serves can be read through it: traversal attempts on every
file-serving route get a 4xx, never a file's bytes."""

import uuid
from pathlib import Path

import httpx
import pytest
from websockets.sync.client import connect

from server.storage.files import SessionFiles
from tests.conftest import LiveServer
from tests.server.helpers import frame, start, ws_url


def test_resolve_refuses_paths_that_leave_the_data_directory(tmp_path: Path) -> None:
    files = SessionFiles(tmp_path)
    assert (
        files.resolve("sessions/x/frames/0.seg") == (tmp_path / "sessions/x/frames/0.seg").resolve()
    )
    for bad in ("../secret", "sessions/../../secret", "/etc/passwd"):
        with pytest.raises(ValueError, match="leaves the data directory"):
            files.resolve(bad)


def test_no_route_serves_a_file_through_a_traversal(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        ws.send(frame(sid, 2))
        ws.recv(timeout=10)
        ws.recv(timeout=10)
    secret = live_server.settings.data_dir / "secret.txt"
    secret.write_text("TOP-SECRET")
    db_head = b"SQLite format 3"
    attempts = [
        f"/api/sessions/{sid}/results/..%2F..%2F..%2Fsecret.txt",
        f"/api/sessions/{sid}/results/%2e%2e%2f%2e%2e%2f%2e%2e%2fsteelscan.db",
        f"/api/sessions/{sid}/results/....//....//secret.txt",
        "/api/sessions/..%2F..%2Fsecret.txt/results/mosaic.png",
        f"/api/sessions/{sid}/mosaic_files/..%2F..%2F/0_0.jpg",
        f"/api/sessions/{sid}/mosaic_files/0/..%2F..%2F..%2Fsecret.txt",
        f"/api/sessions/{sid}/frames/..%2F..%2Fsecret.txt/image",
        f"/api/sessions/{sid}/frames/2%2F..%2F..%2Fsecret.txt/image",
        "/static/..%2F..%2Fserver%2Fconfig.py",
        "/static/../../server/config.py",
        "/static/%2e%2e/%2e%2e/data/secret.txt",
        "/vendor/openseadragon/..%2F..%2F..%2Fpyproject.toml",
        "/viser/..%2F..%2Fsecret.txt",
    ]
    with httpx.Client(base_url=live_server.url) as client:
        for path in attempts:
            r = client.get(path)
            assert 400 <= r.status_code < 500, (path, r.status_code)
            assert b"TOP-SECRET" not in r.content and not r.content.startswith(db_head), path
            assert b"[project]" not in r.content and b"BaseSettings" not in r.content, path
        # the real thing is served
        assert client.get(f"/api/sessions/{sid}/frames/2/image").status_code == 200
