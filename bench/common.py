"""What every benchmark shares: the result type, a robot's session on a station, a job
followed as a dashboard follows it, and small geometric helpers."""

from __future__ import annotations

import time
import uuid
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import httpx
import numpy as np
from numpy.typing import NDArray
from websockets.asyncio.client import ClientConnection, connect

from robot_link.protocol import Message, MessageType, encode_message

Result = dict[str, Any]
FINISHED = ("done", "failed", "cancelled")


@asynccontextmanager
async def robot_session(
    port: int, token: str, sid: uuid.UUID, structure: str, calibration: dict[str, Any]
) -> AsyncIterator[ClientConnection]:
    """A robot's link to the station on loopback ``port``, its session ``sid`` started (as
    message 1, acknowledged): the messages from 2 on are the caller's."""
    async with connect(
        f"ws://127.0.0.1:{port}/ws/robot",
        additional_headers={"Authorization": f"Bearer {token}"},
        max_size=2**22,
    ) as ws:
        start = {"structure": structure, "operator": "bench", "calibration": calibration}
        await ws.send(encode_message(Message(MessageType.SESSION_START, sid, 1, 0.0, start)))
        await ws.recv()
        yield ws


def follow_job(
    client: httpx.Client, job_id: int, every_s: float, until: Callable[[], bool] = lambda: False
) -> dict[str, Any] | None:
    """Poll job ``job_id`` every ``every_s`` through ``client`` (one connection: a client made
    per request loads its TLS context each time) until it is done (its record) or ``until()``
    (None); a job that failed or was cancelled raises."""
    while not until():
        job: dict[str, Any] = client.get(f"/api/jobs/{job_id}").json()
        if job["state"] in FINISHED:
            if job["state"] != "done":
                raise RuntimeError(f"{job.get('kind', 'the')} job {job['state']}: {job['error']}")
            return job
        time.sleep(every_s)
    return None


def speedup(
    name: str, one_s: float, two_s: float, target: float | None = None, **about: Any
) -> Result:
    """A ``scale.`` result: one worker's time against two workers' (the ratio as its value),
    with its ``target`` ratio where it has one and what it measured (``about``)."""
    result: Result = {"name": f"scale.{name}", "value": round(one_s / two_s, 2), "unit": "x"}
    if target is not None:
        result["target"] = target
    return {**result, **about, "one_worker_s": one_s, "two_workers_s": two_s}


def rigid_align_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """``src`` points moved by the rotation and translation that best fit them to ``dst``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((dst - md).T @ (src - ms))
    R = U @ np.diag([1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return (src - ms) @ R.T + md


def similarity_align_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """``src`` points moved by the rotation, uniform scale and translation that best fit them
    to ``dst`` (Umeyama 1991)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D)) / max(float((a**2).sum() / len(src)), 1e-12)
    return scale * a @ R.T + md
