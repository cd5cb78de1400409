"""``steelscan bench scale``: the station on PostgreSQL with Celery workers, on this machine.

- A long simulated session (2,000 camera frames by default, ``--limit`` for another count)
  is recorded through the robot protocol, and a long ToF session (:mod:`bench.scale_map`);
  their stitch, detect and map jobs run on one worker process, and again on two, in three
  rounds a side in alternating order (:func:`round_order`; a short job several times a
  round): the wall time of the stages spread over workers (the stitch's pair
  registrations and bands, detection's frames and mosaic bands, the map's runs of clouds)
  and of the whole jobs, one against two, each the shortest of its runs (a passing
  disturbance on the machine lengthens a run, never shortens one).
- The live link while a big job runs: four robots at a camera's 30 frames/s, in phases
  with the workers idle and phases while they process the session, alternating
  (:mod:`bench.scale_live`); ingest rate and ACK p99 of each.
- Ingest flood (4 robots, 16 frames in flight) on PostgreSQL against SQLite.

PostgreSQL and Redis are Debian's packages started in temporary folders
(:mod:`bench.services`); the station and the workers are separate processes, as deployed.
"""

from __future__ import annotations

import asyncio
import copy
import math
import os
import shutil
import socket
import subprocess
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import httpx

from bench.common import Result, follow_job, robot_session, speedup
from bench.ingest import ROBOTS, drive_robots
from bench.scale_live import live_results
from bench.scale_map import map_results, record_clouds
from bench.services import Postgres, Redis, start_worker, stop_workers
from robot_link.protocol import Message, MessageType, decode_message, encode_message
from robot_link.sim.sweeps import LazySweep, SweepConfig

FRAMES = 2000
FRAME_SIZE = (320, 240)
LIVE_ROBOTS = 4
LIVE_FPS = 30.0
FLOOD_S = 10.0
PX_PER_M = 1000.0
TARGET = 1.6  # a spread stage's ratio, two workers against one
ROUNDS = 3  # of the jobs on one worker and on two, interleaved: each stage's best counts
SAMPLE_S = 40.0  # a job's runs a round: as many as its first run fits in this,
MAX_REPEATS = 4  # and at most this many (a short ``--limit`` session's jobs are short)
# real-time priorities of the station's threads and of PostgreSQL, as docker/compose.yaml
# sets them for a station, its database and workers on one machine (where permitted)
STATION_REALTIME = 10
POSTGRES_REALTIME = 5


def _record(port: int, token: str, frames: int) -> str:
    """A lawn-mower session of ``frames`` frames with odometry, through the robot protocol."""
    sweep = LazySweep(
        SweepConfig(frames=frames, pattern="lawnmower", lanes=8, frame_size=FRAME_SIZE, seed=41)
    )
    sid = uuid.uuid4()
    calib = {"camera": {"px_per_m": PX_PER_M, "T_robot_camera": [0.0, 0.0, 0.0]}}

    async def run() -> None:
        async with robot_session(port, token, sid, "long span", calib) as ws:
            window = 64
            for k in range(frames):
                ok, buf = cv2.imencode(".jpg", sweep[k], [cv2.IMWRITE_JPEG_QUALITY, 90])
                assert ok
                p = sweep.odometry[k]
                meta = {
                    "width": FRAME_SIZE[0],
                    "height": FRAME_SIZE[1],
                    "pose": {"x": p[0] / PX_PER_M, "y": p[1] / PX_PER_M, "yaw": float(p[2])},
                }
                msg = Message(MessageType.FRAME, sid, k + 2, float(k), meta, buf.tobytes())
                await ws.send(encode_message(msg))
                if k >= window:
                    decode_message(await ws.recv())
            for _ in range(min(window, frames)):
                decode_message(await ws.recv())
            end = Message(MessageType.SESSION_END, sid, frames + 2, float(frames), {})
            await ws.send(encode_message(end))
            await ws.recv()

    asyncio.run(run())
    return str(sid)


class _Workers:
    """``steelscan worker`` processes (one job process each) against the station's services,
    started and stopped to a given count."""

    def __init__(self, env: dict[str, str], logs: Path, broker_url: str) -> None:
        self.env, self.logs, self.broker_url = env, logs, broker_url
        self.procs: list[subprocess.Popen[bytes]] = []
        self.started = 0

    def scale_to(self, count: int) -> None:
        """``count`` workers running, each answering the broker (ready for jobs); the
        newest stopped first (a warm shutdown: its task, if any, finishes)."""
        while len(self.procs) > count:
            stop_workers([self.procs.pop()])
        while len(self.procs) < count:
            proc = start_worker(self.env, self.logs / f"worker{self.started}.log")
            self.started += 1
            self.procs.append(proc)
            _await_worker(self.broker_url, proc)

    def stop(self) -> None:
        stop_workers(self.procs)


def _await_worker(broker_url: str, proc: subprocess.Popen[bytes], timeout_s: float = 60.0) -> None:
    """Until worker ``proc`` answers a ping through the broker (its pool started)."""
    from celery import Celery

    name = f"steelscan-{proc.pid}@{socket.gethostname()}"
    app = Celery(broker=broker_url)
    deadline = time.monotonic() + timeout_s
    try:
        while not app.control.ping(destination=[name], timeout=0.5):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"worker {name} did not come up (exit {proc.poll()})")
    finally:
        app.close()


def _job(url: str, sid: str, kind: str) -> tuple[dict, float]:
    """Run a job and follow it, four polls a second; its record and how long it took."""
    t0 = time.perf_counter()
    with httpx.Client(base_url=url) as client:
        job_id = client.post(f"/api/sessions/{sid}/jobs", json={"kind": kind}).json()["id"]
        job = follow_job(client, job_id, 0.25)
        assert job is not None
        return job, time.perf_counter() - t0


def round_order(rounds: int, sides: Sequence[int] = (1, 2)) -> list[int]:
    """The worker counts to run, round after round, the sides' order reversed each round
    (ABBA...): a slow stretch of the machine falls on both sides alike, and every other
    change of side needs no worker started or stopped."""
    return [n for r in range(rounds) for n in (sides if r % 2 == 0 else sides[::-1])]


def best_of(done: Sequence[tuple[dict, float]]) -> tuple[dict, float]:
    """Runs of one job: the last run's record with each stage's shortest time, and the
    shortest time of the whole job (a passing disturbance lengthens a run, never shortens
    one)."""
    job = copy.deepcopy(done[-1][0])
    seconds = job["result"]["seconds"]
    for stage in seconds:
        seconds[stage] = min(j["result"]["seconds"][stage] for j, _ in done)
    return job, min(s for _, s in done)


def interleaved(
    run: Callable[[str, str], tuple[dict, float]],
    scale_to: Callable[[int], None],
    jobs: Sequence[tuple[str, str]],
    rounds: int = ROUNDS,
) -> dict[int, dict[str, tuple[dict, float]]]:
    """Each of ``jobs`` (kind, session) run (``run``: its record and seconds) in ``rounds``
    rounds on one worker and as many on two (``scale_to``), in :func:`round_order`; a job
    shorter than ``SAMPLE_S`` runs several times a round (as often as its first run fits in
    ``SAMPLE_S``, up to ``MAX_REPEATS``), so a short stage is sampled longer. By worker
    count and kind, the best of its runs."""
    done: dict[int, dict[str, list[tuple[dict, float]]]] = {1: {}, 2: {}}
    repeats: dict[str, int] = {}
    for count in round_order(rounds):
        scale_to(count)
        for kind, sid in jobs:
            first = run(kind, sid)
            fits = math.ceil(SAMPLE_S / first[1])
            repeat = repeats.setdefault(kind, max(1, min(MAX_REPEATS, fits)))
            runs = [first] + [run(kind, sid) for _ in range(repeat - 1)]
            done[count].setdefault(kind, []).extend(runs)
    return {n: {kind: best_of(runs) for kind, runs in by.items()} for n, by in done.items()}


def _stage(
    name: str,
    key: str,
    one: dict,
    two: dict,
    stage: str,
    target: float | None = TARGET,
    **about: Any,
) -> Result:
    """A stage of a job (``key`` of its seconds), one worker against two; a spread stage
    has the ``target`` ratio."""
    s1, s2 = one["result"]["seconds"][key], two["result"]["seconds"][key]
    return speedup(name, s1, s2, target, stage=stage, **about)


def _detect_results(one: dict, one_s: float, two: dict, two_s: float, frames: int) -> list[Result]:
    """The detect job's spread stages and whole job, one worker against two."""
    return [
        _stage(
            "parallel_stage_speedup",
            "frames",
            one,
            two,
            "detect job, frames (spread over workers)",
            frames=frames,
            cores=os.cpu_count(),
        ),
        _stage(
            "mosaic_stage_speedup",
            "mosaic",
            one,
            two,
            "detect job, the mosaic: its PNG's pieces unpacked and its bands searched (spread "
            "over workers); components across band seams joined and measured, the mask PNGs "
            "joined on the job's worker",
        ),
        speedup("detect_job_speedup", round(one_s, 1), round(two_s, 1)),
    ]


def _stitch_results(one: dict, one_s: float, two: dict, two_s: float, frames: int) -> list[Result]:
    """The stitch job's spread stages, the stages around them and the whole job, one
    worker against two."""
    return [
        _stage(
            "stitch_pairs_speedup",
            "registrations",
            one,
            two,
            "stitch job, the pair registrations (spread over workers)",
            pairs=one["result"]["pairs"],
        ),
        _stage(
            "stitch_poses_speedup",
            "pairs",
            one,
            two,
            "stitch job, the frames' poses: the pair registrations with the frames prepared, "
            "the lens falloff estimated and the pose graph solved on the job's worker",
            target=None,
        ),
        _stage(
            "stitch_bands_speedup",
            "bands",
            one,
            two,
            "stitch job, the mosaic's bands and the PNG's segments (spread)",
        ),
        _stage(
            "stitch_render_speedup",
            "render",
            one,
            two,
            "stitch job, bands and outputs (the PNG joined, the Deep Zoom pyramid, overview "
            "and coverage saved: one worker each)",
            target=None,
        ),
        speedup(
            "stitch_job_speedup",
            round(one_s, 1),
            round(two_s, 1),
            frames=frames,
            mosaic_px=[one["result"]["width_px"], one["result"]["height_px"]],
        ),
    ]


def _realtime(pid: int) -> int:
    """The real-time priority of a process's main thread (0: normal priority)."""
    policy = os.sched_getscheduler(pid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
    return os.sched_getparam(pid).sched_priority if policy == os.SCHED_RR else 0


def _station(
    data: Path, database_url: str, env: dict[str, str]
) -> tuple[subprocess.Popen[bytes], int, str]:
    from server.config import Settings
    from server.link.robots import create_robot
    from server.loopback import free_port, serve_process
    from server.storage.db import make_engine, make_sessionmaker, upgrade

    upgrade(database_url)
    engine = make_engine(database_url)
    token = create_robot(make_sessionmaker(engine), f"bench-{uuid.uuid4().hex[:6]}")
    engine.dispose()
    Settings(data_dir=data)  # the settings parse
    port = free_port()
    proc = serve_process(
        data,
        port,
        STEELSCAN_DATABASE_URL=database_url,
        STEELSCAN_AUTO_PROCESS="false",
        STEELSCAN_VIEW3D="false",
        STEELSCAN_LIVE_MAP="false",
        STEELSCAN_LIVE_DETECT="false",
        **env,
    )
    return proc, port, token


def _on_workers(
    root: Path, pg: Postgres, redis: Redis, frames: int, limit: int | None
) -> Iterator[Result]:
    """A station on PostgreSQL with Celery workers under ``root``: a long session's and a
    ToF session's jobs on one worker against two, then the live link with and without a
    big job on the workers."""
    queue_env = {"STEELSCAN_JOB_BACKEND": "celery", "STEELSCAN_BROKER_URL": redis.url}
    data = root / "data"
    db_url = pg.new_database()
    station, port, token = _station(
        data, db_url, {**queue_env, "STEELSCAN_REALTIME_PRIORITY": str(STATION_REALTIME)}
    )
    url = f"http://127.0.0.1:{port}"
    workers = _Workers(
        {
            **os.environ,
            **queue_env,
            "STEELSCAN_DATA_DIR": str(data),
            "STEELSCAN_DATABASE_URL": db_url,
        },
        root,
        redis.url,
    )
    try:
        sid = _record(port, token, frames)
        tof_sid = record_clouds(port, token, limit)
        best = interleaved(
            lambda kind, session: _job(url, session, kind),
            workers.scale_to,
            [("stitch", sid), ("detect", sid), ("map", tof_sid)],
        )
        (stitch, stitch_s), (one, one_s), (map1, map1_s) = best[1].values()
        (stitch2, stitch2_s), (two, two_s), (map2, map2_s) = best[2].values()
        yield from map_results(map1, map1_s, map2, map2_s, TARGET)
        yield from _detect_results(one, one_s, two, two_s, frames)
        yield from _stitch_results(stitch, stitch_s, stitch2, stitch2_s, frames)
        workers.scale_to(2)
        realtime = {"station": _realtime(station.pid), "postgresql": pg.realtime}
        for result in live_results(
            port, token, url, sid, LIVE_ROBOTS, LIVE_FPS, [w.pid for w in workers.procs]
        ):
            yield {**result, "realtime_priority": realtime}
    finally:
        workers.stop()
        station.terminate()
        station.wait(timeout=30)


def _flood_rates(root: Path) -> dict[str, float]:
    """Frames per second a station under ``root`` stores of the ingest flood, on a
    PostgreSQL at normal priority (as the SQLite station is) and on SQLite."""
    rates = {}
    flood_pg = Postgres()
    try:
        for name, url_db in (
            ("postgresql", flood_pg.new_database()),
            ("sqlite", f"sqlite:///{root / 'flood' / 'steelscan.db'}"),
        ):
            flood_dir = root / f"flood-{name}"
            proc, fport, ftoken = _station(flood_dir, url_db, {})
            try:
                done, _, secs = drive_robots(fport, ftoken, ROBOTS, FLOOD_S, None)
                rates[name] = sum(a for _, a in done) / secs
            finally:
                proc.terminate()
                proc.wait(timeout=30)
    finally:
        flood_pg.stop()
    return rates


def bench_scale(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Two Celery workers against one on a long session's parallel stage; the live link
    with and without a big job on the workers; ingest on PostgreSQL against SQLite."""
    frames = int(limit or FRAMES)
    root = Path(tempfile.mkdtemp(prefix="steelscan-scale-"))
    pg, redis = Postgres(realtime=POSTGRES_REALTIME), Redis()
    try:
        yield from _on_workers(root, pg, redis, frames, limit)
        rates = _flood_rates(root)
        yield {
            "name": "scale.ingest_flood_postgresql",
            "value": round(rates["postgresql"], 1),
            "unit": "frames/s",
            "baseline": round(rates["sqlite"], 1),
            "baseline_is": "the same flood on SQLite",
            "ratio": round(rates["postgresql"] / rates["sqlite"], 3),
            "robots": ROBOTS,
        }
    finally:
        redis.stop()
        pg.stop()
        shutil.rmtree(root, ignore_errors=True)
