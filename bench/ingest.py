"""``steelscan bench ingest``: how many camera frames per second the ground station stores
durably (file written, SQLite row committed) and acknowledges, with the ACK latency, against
the raw loopback websocket echo rate measured in the same run as the ceiling.

The station runs as its own process (``steelscan serve`` on a scratch data directory, jobs
off). Two loads through the real robot protocol, ~68 KB JPEG-sized frames:

- *flood*: 4 robots, each with 16 frames in flight, for 10 s (or ``--limit``, if shorter):
  the most the station stores;
- *field*: 8 robots at 30 frames/s each (a camera's rate; each camera at its own phase, as
  independent cameras are), for ``--limit`` seconds (60 by default), after the flood's
  dirty pages are written back: sustained rate and the ACK latency of each frame (sent →
  acknowledged after the file is written and its row committed).

- *attacked*: the field load again while a robot floods poison messages, 300 sockets
  trickle request heads and a client tries passwords 8 times a second
  (:mod:`bench.ingest_attack`); its ACK p99 against the quiet field's.

Every frame sent is then counted in the database: none may be lost.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import httpx
import numpy as np
import websockets
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from bench.common import Result
from bench.ingest_attack import LOGINS_PER_S, SLOW_SOCKETS, under_attack
from robot_link.protocol import Message, MessageType, decode_message, encode_message

if TYPE_CHECKING:
    from server.config import Settings

FRAME_BYTES = 68 * 1024
ROBOTS = 4
WINDOW = 16
FIELD_ROBOTS = 8
FIELD_FPS = 30.0


def _payload(rng: np.random.Generator) -> bytes:
    """A 640×480 JPEG of noise, cut or padded to FRAME_BYTES (the station reads its header)."""
    noise = rng.integers(0, 256, (480, 640), dtype=np.uint8)
    ok, buf = cv2.imencode(".jpg", noise, [cv2.IMWRITE_JPEG_QUALITY, 70])
    assert ok
    data = buf.tobytes()
    return data[:FRAME_BYTES] + bytes(max(0, FRAME_BYTES - len(data)))


async def _robot(
    url: str,
    token: str,
    seconds: float,
    latencies: list[float],
    rng: np.random.Generator,
    fps: float | None = None,
) -> tuple[str, int]:
    """Stream frames for ``seconds`` (as fast as the window allows, or at ``fps``); returns
    the session id and how many were acknowledged."""
    sid = uuid.uuid4()
    payload = _payload(rng)
    sent_at: dict[int, float] = {}
    acked = 0
    window = asyncio.Semaphore(WINDOW)
    async with connect(
        url,
        additional_headers={"Authorization": f"Bearer {token}"},
        max_size=2**20,
        compression=None,
    ) as ws:
        await ws.send(
            encode_message(
                Message(
                    MessageType.SESSION_START, sid, 1, time.time(), {"structure": "ingest bench"}
                )
            )
        )
        decode_message(await ws.recv())
        done = asyncio.Event()

        async def reader() -> None:
            nonlocal acked
            async for raw in ws:
                m = decode_message(raw)  # type: ignore[arg-type]
                if m.type is MessageType.ACK and m.seq in sent_at:
                    latencies.append(time.perf_counter() - sent_at.pop(m.seq))
                    acked += 1
                    window.release()
                if done.is_set() and not sent_at:
                    return

        task = asyncio.create_task(reader())
        t_start = time.perf_counter()
        if fps is not None:  # independent cameras are not in step: each starts at its own phase
            t_start += float(rng.uniform(0.0, 1.0 / fps))
        seq, end = 2, t_start + seconds
        while time.perf_counter() < end:
            if fps is not None:  # a camera's pace: frame k leaves at k / fps
                await asyncio.sleep(max(0.0, t_start + (seq - 2) / fps - time.perf_counter()))
            await window.acquire()
            meta = {"width": 640, "height": 480, "pose": {"x": 0.0, "y": 0.0, "yaw": 0.0}}
            sent_at[seq] = time.perf_counter()
            await ws.send(
                encode_message(Message(MessageType.FRAME, sid, seq, time.time(), meta, payload))
            )
            seq += 1
        done.set()
        await asyncio.wait_for(task, 60)
    return str(sid), acked


async def _echo_ceiling(seconds: float) -> float:
    """Frames per second a bare ``websockets`` echo on loopback manages (same size, same window)."""

    async def echo(ws: websockets.asyncio.server.ServerConnection) -> None:
        try:
            async for _ in ws:
                await ws.send(b"ok")
        except websockets.ConnectionClosed:
            pass

    async with serve(echo, "127.0.0.1", 0, max_size=2**20, compression=None) as server:
        port = server.sockets[0].getsockname()[1]
        payload = _payload(np.random.default_rng(0))
        async with connect(f"ws://127.0.0.1:{port}", max_size=2**20, compression=None) as ws:
            window = asyncio.Semaphore(WINDOW)
            count = 0

            async def reader() -> None:
                nonlocal count
                async for _ in ws:
                    count += 1
                    window.release()

            task = asyncio.create_task(reader())
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                await window.acquire()
                await ws.send(payload)
            elapsed = time.perf_counter() - t0
            task.cancel()
            return count / elapsed


def drive_robots(
    port: int, token: str, robots: int, seconds: float, fps: float | None
) -> tuple[list[tuple[str, int]], list[float], float]:
    """``robots`` robots streaming frames for ``seconds`` (at ``fps``, or as fast as the window
    allows): each one's (session, frames acknowledged), every ACK latency (s), the wall time."""
    latencies: list[float] = []
    url = f"ws://127.0.0.1:{port}/ws/robot"

    async def all_robots() -> list[tuple[str, int]]:
        rngs = [np.random.default_rng(k) for k in range(robots)]
        return await asyncio.gather(*(_robot(url, token, seconds, latencies, r, fps) for r in rngs))

    t0 = time.perf_counter()
    results = asyncio.run(all_robots())
    return results, latencies, time.perf_counter() - t0


Run = tuple[list[tuple[str, int]], list[float], float]


@dataclass
class _Loads:
    """What the three loads measured: each one's (session, frames acknowledged), every ACK
    latency (s) and the wall time (s); what the attackers saw; the frames the station
    stored per session."""

    flood: Run
    field: Run
    attacked: Run
    attackers: dict[str, Any]
    stored: dict[str, int]


def _station(root: Path) -> tuple[Settings, str, str]:
    """A station's settings on a scratch data directory under ``root``, its database made,
    and the tokens of two robot accounts: the bench's and the attacker's."""
    from server.config import Settings
    from server.link.robots import create_robot
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    settings = Settings(data_dir=root / "data")
    upgrade(settings.resolved_database_url())
    engine = make_engine(settings.resolved_database_url())
    token = create_robot(make_sessionmaker(engine), "bench")
    attacker = create_robot(make_sessionmaker(engine), "attacker")
    engine.dispose()
    return settings, token, attacker


def _run_loads(port: int, token: str, attacker: str, field_seconds: float) -> _Loads:
    """The flood, the field load and the field load under attack against the station on
    ``port``, then the frames it stored of every session."""
    flood = drive_robots(port, token, ROBOTS, min(10.0, field_seconds), None)
    # the flood leaves a gigabyte or more of dirty pages; written back now, or the
    # field phase would measure the kernel's writeback of the flood
    os.sync()
    field = drive_robots(port, token, FIELD_ROBOTS, field_seconds, FIELD_FPS)
    os.sync()
    attacked: list[Run] = []
    attackers = under_attack(
        port,
        attacker,
        lambda: attacked.append(drive_robots(port, token, FIELD_ROBOTS, field_seconds, FIELD_FPS)),
    )
    stored = {
        sid: httpx.get(f"http://127.0.0.1:{port}/api/sessions/{sid}", timeout=30).json()["frames"]
        for sid, _ in flood[0] + field[0] + attacked[0][0]
    }
    return _Loads(flood, field, attacked[0], attackers, stored)


def _flood_result(flood: Run, ceiling: float) -> Result:
    """The flood's stored frames per second against the echo ``ceiling``."""
    robots, latencies, seconds = flood
    rate = sum(a for _, a in robots) / seconds
    return {
        "name": "ingest.frames_per_second",
        "value": round(rate, 1),
        "unit": "frames/s",
        "target": 2000,
        "baseline": round(ceiling, 1),
        "ratio": round(rate / ceiling, 3),
        "baseline_is": "bare websockets echo on loopback",
        "robots": ROBOTS,
        "window": WINDOW,
        "frame_kb": FRAME_BYTES // 1024,
        "seconds": round(seconds, 1),
        "ack_latency_p50_ms": round(float(np.percentile(np.array(latencies) * 1000, 50)), 2),
    }


def _field_results(field: Run) -> Iterator[Result]:
    """The field load's sustained rate and its ACK latency p50 and p99."""
    robots, latencies, seconds = field
    lat = np.array(latencies) * 1000
    yield {
        "name": "ingest.field_frames_per_second",
        "value": round(sum(a for _, a in robots) / seconds, 1),
        "unit": "frames/s",
        "offered": FIELD_ROBOTS * FIELD_FPS,
        "robots": FIELD_ROBOTS,
        "fps_per_robot": FIELD_FPS,
        "seconds": round(seconds, 1),
    }
    yield {
        "name": "ingest.ack_latency_p50",
        "value": round(float(np.percentile(lat, 50)), 2),
        "unit": "ms",
        "load": "field",
    }
    yield {
        "name": "ingest.ack_latency_p99",
        "value": round(float(np.percentile(lat, 99)), 2),
        "unit": "ms",
        "target": 2.0,
        "load": "field",
    }


def _attack_result(loads: _Loads) -> Result:
    """The field load's ACK p99 under attack against the quiet field's, and the attacks."""
    quiet_p99 = float(np.percentile(np.array(loads.field[1]) * 1000, 99))
    attacked_p99 = float(np.percentile(np.array(loads.attacked[1]) * 1000, 99))
    return {
        "name": "ingest.ack_latency_p99_under_attack",
        "value": round(attacked_p99, 2),
        "unit": "ms",
        "baseline": round(quiet_p99, 2),
        "baseline_is": "the same field load without attackers",
        "ratio": round(attacked_p99 / max(quiet_p99, 1e-9), 3),
        "target_ratio": 2.0,
        "attacks": {
            "poison_robot": loads.attackers.get("poison_robot"),
            "slow_sockets": SLOW_SOCKETS,
            "slow_sockets_closed_by_station": loads.attackers.get("slow_sockets_closed"),
            "logins_per_s": LOGINS_PER_S,
            "login_answers": loads.attackers.get("login_answers"),
        },
        "acked": sum(a for _, a in loads.attacked[0]),
    }


def _lost_result(loads: _Loads) -> Result:
    """Frames acknowledged to the robots that the station did not store (none may be)."""
    all_acked = {sid: a for sid, a in loads.flood[0] + loads.field[0] + loads.attacked[0]}
    return {
        "name": "ingest.lost",
        "value": sum(all_acked.values()) - sum(loads.stored.values()),
        "unit": "frames",
        "acked": sum(all_acked.values()),
        "stored": sum(loads.stored.values()),
    }


def bench_ingest(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Most frames per second stored durably (flood) against the echo ceiling, then the
    sustained rate, ACK latency and losses of several robots at a camera's 30 frames/s."""
    from server.loopback import free_port, serve_process

    field_seconds = float(limit or 60)
    root = Path(tempfile.mkdtemp(prefix="steelscan-ingest-"))
    try:
        settings, token, attacker = _station(root)
        port = free_port()
        proc = serve_process(
            settings.data_dir, port, STEELSCAN_AUTO_PROCESS="false", STEELSCAN_VIEW3D="false"
        )
        try:
            loads = _run_loads(port, token, attacker, field_seconds)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        ceiling = asyncio.run(_echo_ceiling(min(5.0, field_seconds)))
        yield _flood_result(loads.flood, ceiling)
        yield from _field_results(loads.field)
        yield _attack_result(loads)
        yield _lost_result(loads)
    finally:
        shutil.rmtree(root, ignore_errors=True)
