"""The attack phase of ``steelscan bench ingest``: while the honest robots stream at a
camera's rate, one robot floods the station with poison messages (seq beyond 2**63, as fast
as it can), 300 sockets from another address trickle a partial request head, and a client
tries passwords for random user names several times a second."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import time
import uuid
from collections.abc import Callable

import httpx
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from robot_link.protocol import HEADER, Message, MessageType, encode_message

SLOW_SOCKETS = 300
LOGINS_PER_S = 8.0
RECONNECT_S = 0.01  # the poisoning robot reconnects up to 100 times a second when cut off
ATTACKER_ADDRESS = "127.0.0.2"  # the slow sockets come from here; the robots from 127.0.0.1


def _poison(sid: uuid.UUID, seq: int) -> bytes:
    """A telemetry message whose seq no station can store (the encoder refuses to make it)."""
    data = bytearray(encode_message(Message(MessageType.TELEMETRY, sid, 1, time.time(), {})))
    struct.pack_into("<Q", data, 24, seq)
    assert HEADER.unpack_from(data)[5] == seq
    return bytes(data)


async def _flooding_robot(url: str, token: str, stop: asyncio.Event) -> dict[str, int]:
    """Poison messages as fast as the link takes them, reconnecting whenever the station
    cuts the link or refuses it; how many were answered and how often it was cut off."""
    answered, cut = 0, 0
    sid = uuid.uuid4()
    seq = 2**63
    while not stop.is_set():
        try:
            async with connect(
                url, additional_headers={"Authorization": f"Bearer {token}"}, compression=None
            ) as ws:

                async def reader(ws=ws) -> None:  # type: ignore[no-untyped-def]
                    nonlocal answered
                    async for _ in ws:
                        answered += 1

                task = asyncio.create_task(reader())
                try:
                    while not stop.is_set():
                        await ws.send(_poison(sid, seq))
                        seq += 1
                        if seq % 64 == 0:
                            await asyncio.sleep(0)  # let the reader run
                finally:
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await task
        except (OSError, ConnectionClosed, InvalidHandshake):
            cut += 1
            await asyncio.sleep(RECONNECT_S)
    return {"answered": answered, "cut_off": cut}


async def _slow_sockets(port: int, stop: asyncio.Event) -> int:
    """Open SLOW_SOCKETS connections sending a request head that never ends, and keep
    re-opening those the station closes; how many it closed."""
    closed = 0
    loop = asyncio.get_running_loop()

    def open_one() -> socket.socket | None:
        s = socket.socket()
        try:
            s.bind((ATTACKER_ADDRESS, 0))
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", port))
        except OSError:
            s.close()
            return None
        return s

    socks = [s for s in (open_one() for _ in range(SLOW_SOCKETS)) if s is not None]
    await asyncio.sleep(0.2)
    for s in socks:
        with contextlib.suppress(OSError):
            s.send(b"GET /api/health HTTP/1.1\r\nHost: station\r\nX-Slow: ")
    while not stop.is_set():
        await asyncio.sleep(1.0)
        for i, s in enumerate(socks):
            try:
                gone = s.recv(1) == b""
            except BlockingIOError:
                continue
            except OSError:
                gone = True
            if gone:
                closed += 1
                s.close()
                fresh = await loop.run_in_executor(None, open_one)
                if fresh is not None:
                    socks[i] = fresh
    for s in socks:
        s.close()
    return closed


async def _login_flood(base: str, stop: asyncio.Event) -> dict[int, int]:
    """Wrong passwords for random user names at LOGINS_PER_S; answers by status code."""
    codes: dict[int, int] = {}
    async with httpx.AsyncClient(base_url=base, timeout=30) as client:
        while not stop.is_set():
            t0 = time.perf_counter()
            r = await client.post(
                "/api/auth/token", data={"username": f"u{uuid.uuid4().hex}", "password": "x"}
            )
            codes[r.status_code] = codes.get(r.status_code, 0) + 1
            await asyncio.sleep(max(0.0, 1 / LOGINS_PER_S - (time.perf_counter() - t0)))
    return codes


def under_attack(port: int, attacker_token: str, honest: Callable[[], object]) -> dict:
    """Run ``honest`` (the field load, in this thread) while the three attacks run in
    another; what the attackers saw."""
    import threading

    results: dict = {}
    started = threading.Event()
    stopping: list[Callable[[], None]] = []

    def attack() -> None:
        async def main() -> None:
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            stopping.append(lambda: loop.call_soon_threadsafe(stop.set))
            started.set()
            flood, slow, logins = await asyncio.gather(
                _flooding_robot(f"ws://127.0.0.1:{port}/ws/robot", attacker_token, stop),
                _slow_sockets(port, stop),
                _login_flood(f"http://127.0.0.1:{port}", stop),
            )
            results.update(poison_robot=flood, slow_sockets_closed=slow, login_answers=logins)

        asyncio.run(main())

    thread = threading.Thread(target=attack, name="attackers")
    thread.start()
    started.wait(30)
    time.sleep(1.0)  # the attacks under way before the robots start
    try:
        honest()
    finally:
        for stop in stopping:
            stop()
        thread.join(timeout=120)
    return results
