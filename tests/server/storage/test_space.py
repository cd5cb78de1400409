"""A full disk never costs a robot its data: the station answers "retry later" (below its
reserve, or when the filesystem itself is full), the robot keeps its spool, and everything
is stored once there is room again."""

from __future__ import annotations

import asyncio
import errno
import os
import shutil
import sqlite3
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx
import pytest
from sqlalchemy.exc import OperationalError

from robot_link.client import LinkError, RobotLink
from robot_link.protocol import MessageType
from robot_link.spool import Spool
from server.config import Settings
from server.errors import IngestError
from server.loopback import BackgroundServer, free_port
from server.storage.space import DiskReserve, is_disk_full
from tests.conftest import make_token
from tests.server.helpers import JPEG


def test_the_reserve_refuses_with_retry_and_reports_itself(tmp_path: Path) -> None:
    DiskReserve(tmp_path, reserve_bytes=0).claim(10)
    free = shutil.disk_usage(tmp_path).free
    full = DiskReserve(tmp_path, reserve_bytes=2 * free)
    with pytest.raises(IngestError, match="retry later") as info:
        full.claim(1)
    assert info.value.retry
    assert not full.status().accepting and full.status().free_bytes > 0
    # claims between two looks at the disk count against it
    tight = DiskReserve(tmp_path, reserve_bytes=free - 3 * 2**20, interval_s=3600)
    tight.claim(2**20)
    tight.claim(2**20)
    with pytest.raises(IngestError):
        tight.claim(2 * 2**20)


def test_a_full_disk_is_recognised_through_the_layers_that_wrap_it() -> None:
    full = sqlite3.OperationalError("database or disk is full")
    assert is_disk_full(OperationalError("COMMIT", {}, full))
    assert is_disk_full(OSError(errno.ENOSPC, "No space left on device"))
    try:
        try:
            raise OSError(errno.EDQUOT, "Disk quota exceeded")
        except OSError:
            raise RuntimeError("write failed")  # noqa: B904  chained implicitly, as in a handler
    except RuntimeError as wrapped:
        assert is_disk_full(wrapped)
    assert not is_disk_full(sqlite3.OperationalError("database is locked"))
    assert not is_disk_full(OSError(errno.EACCES, "Permission denied"))


async def _send_session(link: RobotLink, frames: int) -> None:
    await link.send(MessageType.SESSION_START, {"structure": "full disk"})
    for i in range(frames):
        await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG + bytes([i]))
    await link.send(MessageType.SESSION_END, {"reason": "done"})


def test_below_the_reserve_robots_keep_their_data_until_there_is_room(
    tmp_path: Path, database_url: str
) -> None:
    full = Settings(
        database_url=database_url,
        data_dir=tmp_path / "data",
        job_workers=1,
        auto_process=False,
        min_free_bytes=2**60,
    )
    token = make_token(full)
    spool_dir = tmp_path / "spool"

    async def while_full(url: str) -> uuid.UUID:
        link = RobotLink(url, token, max_backoff_s=0.5, spool=Spool(spool_dir, fsync=False))
        await link.start()
        await _send_session(link, 5)
        with pytest.raises(LinkError, match="7 messages still unacknowledged"):
            await link.flush(timeout_s=3)
        assert link.stats.errors >= 7 and link.stats.acked == 0
        await link.close()
        return link.session_id

    server = BackgroundServer(full, free_port())
    server.start()
    try:
        sid = asyncio.run(while_full(server.url))
        health = httpx.get(f"{server.url}/api/health").json()
        assert health["storage"]["accepting"] is False
        assert httpx.get(f"{server.url}/api/sessions/{sid}").status_code == 404
    finally:
        server.stop()
    assert len(Spool(spool_dir)) == 7  # nothing deleted on the robot

    room = full.model_copy(update={"min_free_bytes": 0})
    server = BackgroundServer(room, free_port())
    server.start()
    try:

        async def with_room() -> None:
            link = RobotLink(server.url, token, spool=Spool(spool_dir, fsync=False))
            await link.start()
            await link.flush(timeout_s=30)
            await link.close()

        asyncio.run(with_room())
        session = httpx.get(f"{server.url}/api/sessions/{sid}").json()
        assert session["frames"] == 5 and session["status"] == "ended"
        assert httpx.get(f"{server.url}/api/health").json()["storage"]["accepting"] is True
    finally:
        server.stop()
    assert len(Spool(spool_dir)) == 0


def _can_mount_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = "d=$(mktemp -d) && mount -t tmpfs -o size=1m tmpfs $d"
    return (
        subprocess.run(["unshare", "-rm", "sh", "-c", probe], capture_output=True).returncode == 0
    )


@pytest.mark.slow
@pytest.mark.skipif(
    not _can_mount_tmpfs(), reason="no private mount namespace (unshare -rm) on this machine"
)
def test_a_full_filesystem_makes_the_robot_wait_not_forget(tmp_path: Path) -> None:
    """The data dir on a tmpfs (mounted in a private mount namespace) that a filler file
    fills to its last 800 kB; the simulator's whole inspection cannot be stored, the sim exits 2
    keeping its spool, and once the filler is gone its spool is delivered in full."""
    data = tmp_path / "data"
    data.mkdir()
    token_file = tmp_path / "token"
    port = free_port()
    steelscan = [sys.executable, "-m", "server.cli"]
    script = (
        f"mount -t tmpfs -o size=6m tmpfs {data} && "
        f"{' '.join(steelscan)} admin create-robot crawler --data-dir {data} > {token_file} && "
        f"avail=$(df --output=avail -B1 {data} | tail -n 1) && "
        f"head -c $((avail - 800000)) /dev/zero > {data}/filler && "
        f"exec {' '.join(steelscan)} serve --data-dir {data} --port {port}"
    )
    env = {**os.environ, "STEELSCAN_MIN_FREE_BYTES": "0", "STEELSCAN_AUTO_PROCESS": "false"}
    # the station's log goes to a file: a pipe nobody reads would stall it once full
    log_path = tmp_path / "station.log"
    station_log = log_path.open("wb")
    serve = subprocess.Popen(
        ["unshare", "-rm", "sh", "-c", script],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=station_log,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            assert serve.poll() is None, log_path.read_text()[-4000:]
            try:
                if httpx.get(f"{url}/api/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "station did not start"
            time.sleep(0.2)
        token = token_file.read_text().split()[-1]
        spool = tmp_path / "spool"
        sim = subprocess.run(
            [
                *steelscan,
                "sim",
                "--server",
                url,
                "--token",
                token,
                "--exit-when-done",
                "--spool",
                str(spool),
                "--lanes",
                "1",
                "--time-scale",
                "0",
                "--flush-timeout",
                "5",
            ],
            capture_output=True,
            text=True,
            timeout=240,
        )
        assert sim.returncode == 2 and "unacknowledged" in sim.stderr, sim.stderr[-2000:]
        left = len(Spool(spool))
        assert left > 0  # what the station could not store is still on the robot
        os.remove(f"/proc/{serve.pid}/root{data}/filler")  # room again (seen from the namespace)

        async def deliver() -> RobotLink:
            link = RobotLink(url, token, spool=Spool(spool, fsync=False))
            await link.start()
            await link.flush(timeout_s=60)
            await link.close()
            return link

        try:
            link = asyncio.run(deliver())
        except LinkError as exc:
            raise AssertionError(f"{exc}; station log:\n{log_path.read_text()[-4000:]}") from exc
        session = httpx.get(f"{url}/api/sessions/{link.session_id}").json()
        assert session["status"] == "ended" and session["frames"] > 0 and session["clouds"] > 0
        assert len(Spool(spool)) == 0
        inside = Path(f"/proc/{serve.pid}/root{data}")  # SQLite would resolve the link
        for name in ("steelscan.db", "steelscan.db-wal"):
            if (inside / name).exists():
                shutil.copyfile(inside / name, tmp_path / name)
        db = sqlite3.connect(tmp_path / "steelscan.db")
        try:
            stored = dict(db.execute("SELECT seq, type FROM received_messages"))
        finally:
            db.close()
        last = max(stored)
        assert sorted(stored) == list(range(1, last + 1))  # every message the sim sent
        assert stored[last] == "SESSION_END"
    finally:
        serve.terminate()
        serve.wait(timeout=30)
        station_log.close()
