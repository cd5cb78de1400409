"""SIGKILL of the ground station in the middle of a session: nothing acknowledged is lost,
the database stays consistent, and the robot's resends fill the gap exactly once."""

import asyncio
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, text

from robot_link.client import RobotLink
from robot_link.protocol import MessageType
from robot_link.spool import Spool
from server.config import Settings
from server.loopback import free_port, serve_process
from tests.conftest import make_token
from tests.server.helpers import JPEG

pytestmark = pytest.mark.slow  # an end-to-end run


def serve(data_dir: Path, port: int, database_url: str = "") -> subprocess.Popen:
    env = {"STEELSCAN_DATABASE_URL": database_url} if database_url else {}
    return serve_process(data_dir, port, STEELSCAN_AUTO_PROCESS="false", **env)


def test_sigkill_mid_session_loses_nothing(tmp_path: Path, database_url: str) -> None:
    data = tmp_path / "data"
    token = make_token(Settings(data_dir=data, database_url=database_url))
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    first = serve(data, port, database_url)
    frames = 60

    async def robot() -> tuple[str, subprocess.Popen, RobotLink]:
        link = RobotLink(
            url, token, max_backoff_s=0.3, spool=Spool(tmp_path / "spool", fsync=False)
        )
        await link.start()
        await link.send(MessageType.SESSION_START, {"structure": "killed station"})
        for i in range(frames):
            await link.send(
                MessageType.FRAME, {"width": 640, "height": 480}, JPEG + i.to_bytes(2, "little")
            )
            if i == frames // 2:
                await asyncio.sleep(0.3)  # some of it acknowledged, some in flight...
                first.send_signal(signal.SIGKILL)  # ...when the station dies without warning
                await asyncio.to_thread(first.wait)
                second = await asyncio.to_thread(serve, data, port, database_url)
            await asyncio.sleep(0.005)
        await link.flush(timeout_s=60)
        await link.close()
        return str(link.session_id), second, link

    sid, second, link = asyncio.run(robot())
    assert link.stats.reconnects >= 1
    try:
        session = httpx.get(f"{url}/api/sessions/{sid}").raise_for_status().json()
        assert session["frames"] == frames  # every frame, none twice
    finally:
        second.terminate()
        second.wait(timeout=30)
    if database_url.startswith("sqlite"):
        check = sqlite3.connect(data / "steelscan.db")
        assert check.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        check.close()
    engine = create_engine(database_url)
    with engine.connect() as db:
        rows = db.execute(
            text("SELECT COUNT(*), COUNT(DISTINCT seq) FROM frames WHERE session_id = :s"),
            {"s": sid},
        ).one()
        assert tuple(rows) == (frames, frames)
        # every row's payload is where the row says: a JPEG of the stored size in its segment
        # file (bytes of an append the crash cut short may follow, but no row points at them)
        from server.storage.files import SessionFiles

        store = SessionFiles(data)
        for path, offset, size in db.execute(
            text("SELECT path, data_offset, size_bytes FROM frames WHERE session_id = :s"),
            {"s": sid},
        ):
            payload = store.read(path, offset, size)
            assert payload.startswith(b"\xff\xd8") and len(payload) == size
    engine.dispose()


def _alive_children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` and that have not exited (zombies count as gone)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, ppid = stat.read_text().rsplit(")", 1)[1].split()[:2]
        except (OSError, ValueError):
            continue
        if int(ppid) == pid and state != "Z":
            found.append(int(stat.parent.name))
    return found


def _alive(pids: list[int]) -> list[int]:
    alive = []
    for p in pids:
        try:
            state = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.append(p)
    return alive


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_job_workers_end_with_the_station(
    tmp_path: Path, database_url: str, how: signal.Signals
) -> None:
    """Killed or stopped, the station leaves no worker process behind."""
    data = tmp_path / "data"
    token = make_token(Settings(data_dir=data, database_url=database_url))
    port = free_port()
    proc = serve(data, port, database_url)
    url = f"http://127.0.0.1:{port}"
    try:

        async def record() -> str:
            link = RobotLink(url, token)
            await link.start()
            await link.send(MessageType.SESSION_START, {"structure": "workers"})
            await link.send(MessageType.FRAME, {"width": 640, "height": 480}, JPEG)
            await link.flush(timeout_s=30)
            await link.close()
            return str(link.session_id)

        sid = asyncio.run(record())
        job = httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "stitch"}).json()
        for _ in range(600):
            state = httpx.get(f"{url}/api/jobs/{job['id']}").json()["state"]
            if state in ("done", "failed"):
                break
            time.sleep(0.1)
        workers = _alive_children(proc.pid)
        assert workers  # the job ran in a worker process, which the pool keeps
    finally:
        proc.send_signal(how)
        proc.wait(timeout=60)
    deadline = time.monotonic() + 10
    while _alive(workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(workers)
