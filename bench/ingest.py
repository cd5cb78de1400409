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
from pathlib import Path

import cv2
import httpx
import numpy as np
import websockets
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from bench.common import Result
from bench.ingest_attack import LOGINS_PER_S, SLOW_SOCKETS, under_attack
from robot_link.protocol import Message, MessageType, decode_message, encode_message

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


def bench_ingest(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Most frames per second stored durably (flood) against the echo ceiling, then the
    sustained rate, ACK latency and losses of several robots at a camera's 30 frames/s."""
    from server.config import Settings
    from server.link.robots import create_robot
    from server.loopback import free_port, serve_process
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    field_seconds = float(limit or 60)
    root = Path(tempfile.mkdtemp(prefix="steelscan-ingest-"))
    try:
        settings = Settings(data_dir=root / "data")
        upgrade(settings.resolved_database_url())
        engine = make_engine(settings.resolved_database_url())
        token = create_robot(make_sessionmaker(engine), "bench")
        attacker = create_robot(make_sessionmaker(engine), "attacker")
        engine.dispose()
        port = free_port()
        proc = serve_process(
            settings.data_dir, port, STEELSCAN_AUTO_PROCESS="false", STEELSCAN_VIEW3D="false"
        )
        try:
            flood, flood_lat, flood_s = drive_robots(
                port, token, ROBOTS, min(10.0, field_seconds), None
            )
            # the flood leaves a gigabyte or more of dirty pages; written back now, or the
            # field phase would measure the kernel's writeback of the flood
            os.sync()
            field, field_lat, field_s = drive_robots(
                port, token, FIELD_ROBOTS, field_seconds, FIELD_FPS
            )
            os.sync()
            attacked: list[tuple[list[tuple[str, int]], list[float], float]] = []
            attackers = under_attack(
                port,
                attacker,
                lambda: attacked.append(
                    drive_robots(port, token, FIELD_ROBOTS, field_seconds, FIELD_FPS)
                ),
            )
            field_attacked, attacked_lat, _ = attacked[0]
            stored = {
                sid: httpx.get(f"http://127.0.0.1:{port}/api/sessions/{sid}", timeout=30).json()[
                    "frames"
                ]
                for sid, _ in flood + field + field_attacked
            }
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        ceiling = asyncio.run(_echo_ceiling(min(5.0, field_seconds)))
        acked = sum(a for _, a in flood)
        rate = acked / flood_s
        yield {
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
            "seconds": round(flood_s, 1),
            "ack_latency_p50_ms": round(float(np.percentile(np.array(flood_lat) * 1000, 50)), 2),
        }
        lat = np.array(field_lat) * 1000
        field_acked = sum(a for _, a in field)
        yield {
            "name": "ingest.field_frames_per_second",
            "value": round(field_acked / field_s, 1),
            "unit": "frames/s",
            "offered": FIELD_ROBOTS * FIELD_FPS,
            "robots": FIELD_ROBOTS,
            "fps_per_robot": FIELD_FPS,
            "seconds": round(field_s, 1),
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
        quiet_p99 = float(np.percentile(lat, 99))
        attacked_p99 = float(np.percentile(np.array(attacked_lat) * 1000, 99))
        yield {
            "name": "ingest.ack_latency_p99_under_attack",
            "value": round(attacked_p99, 2),
            "unit": "ms",
            "baseline": round(quiet_p99, 2),
            "baseline_is": "the same field load without attackers",
            "ratio": round(attacked_p99 / max(quiet_p99, 1e-9), 3),
            "target_ratio": 2.0,
            "attacks": {
                "poison_robot": attackers.get("poison_robot"),
                "slow_sockets": SLOW_SOCKETS,
                "slow_sockets_closed_by_station": attackers.get("slow_sockets_closed"),
                "logins_per_s": LOGINS_PER_S,
                "login_answers": attackers.get("login_answers"),
            },
            "acked": sum(a for _, a in field_attacked),
        }
        all_acked = {sid: a for sid, a in flood + field + field_attacked}
        yield {
            "name": "ingest.lost",
            "value": sum(all_acked.values()) - sum(stored.values()),
            "unit": "frames",
            "acked": sum(all_acked.values()),
            "stored": sum(stored.values()),
        }
    finally:
        shutil.rmtree(root, ignore_errors=True)
