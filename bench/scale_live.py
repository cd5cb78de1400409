"""The live link beside busy workers, for ``steelscan bench scale``: phases with the
workers idle and phases with a big job on them, alternating, so that a drift of the
machine (other programs, a cache warming) falls on both alike.

One phase's ACK p99 rests on its dozen slowest acknowledgements, and quiet phases of the
same run differ by up to half of it; each side's p99 is therefore taken over all its
phases' latencies together, and every phase's own p99 is reported beside it.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import httpx
import numpy as np
import psutil

from bench.common import FINISHED, Result, follow_job
from bench.ingest import drive_robots
from server.jobs.priority import put_the_station_first

PAIRS = 4  # quiet and busy phases, alternating
ROBOTS_REALTIME = 1  # the simulated robots' priority: robots have machines of their own
PHASE_S = 10.0
RAMP_S = 4.0  # after a job is sent, before the robots start: its parts spread over workers
FOLLOW_S = 1.0  # the dashboard's jobs bar reads a running job's progress this often
IDLE_CORES = 0.1  # the workers' CPU use below which they count as idle
IDLE_WINDOW_S = 0.5
IDLE_WAIT_S = 60.0  # a cancelled job's processes stop at their next check, within this


def cpu_s(pids: list[int]) -> float:
    """CPU seconds used so far by the processes ``pids``, their children and the children
    that ended."""
    total = 0.0
    for pid in pids:
        try:
            proc = psutil.Process(pid)
            for p in [proc, *proc.children(recursive=True)]:
                t = p.cpu_times()
                total += t.user + t.system + t.children_user + t.children_system
        except psutil.Error:  # ended meanwhile
            continue
    return total


@contextmanager
def robots_apart() -> Iterator[int]:
    """This process's threads (the simulated robots) at real-time priority
    :data:`ROBOTS_REALTIME` for the ``with`` block, then normal again; the priority taken
    (0 where refused). Robots in the field run on machines of their own: a job on the
    station's cores delays their frames' handling on the station, never their own sending
    and receiving, which here would otherwise wait behind the jobs for the kernel's tick."""
    raised = ROBOTS_REALTIME if put_the_station_first(ROBOTS_REALTIME) else 0
    try:
        yield raised
    finally:
        if raised:
            for tid in os.listdir("/proc/self/task"):
                try:
                    os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))
                except OSError:  # ended meanwhile
                    continue


def wait_idle(workers_cpu_s: Callable[[], float]) -> None:
    """Until the processes whose CPU time ``workers_cpu_s`` gives use less than
    ``IDLE_CORES`` (a cancelled job's processes run on to their next check)."""
    deadline = time.monotonic() + IDLE_WAIT_S
    while time.monotonic() < deadline:
        before = workers_cpu_s()
        time.sleep(IDLE_WINDOW_S)
        if workers_cpu_s() - before < IDLE_CORES * IDLE_WINDOW_S:
            return
    raise RuntimeError(f"the workers are still busy {IDLE_WAIT_S:.0f} s after their job ended")


def p99_ms(latencies: list[float]) -> float:
    return round(float(np.percentile(np.array(latencies) * 1000, 99)), 2)


class _Busy:
    """Detect jobs back to back on the workers, each followed as the dashboard follows it,
    until :meth:`stop`, which cancels the one running and waits until it has ended."""

    def __init__(self, url: str, sid: str) -> None:
        self.url, self.sid = url, sid
        self.job_id: int | None = None
        self.error: Exception | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="busy-jobs")

    def start(self) -> _Busy:
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self._follow()
        except Exception as exc:  # raised again on the benchmark's thread by stop()
            self.error = exc

    def _follow(self) -> None:
        with httpx.Client(base_url=self.url, timeout=60) as client:
            while not self._stop.is_set():
                post = client.post(f"/api/sessions/{self.sid}/jobs", json={"kind": "detect"})
                self.job_id = post.json()["id"]
                follow_job(client, self.job_id, FOLLOW_S, self._stop.is_set)
            client.post(f"/api/jobs/{self.job_id}/cancel")
            while client.get(f"/api/jobs/{self.job_id}").json()["state"] not in FINISHED:
                time.sleep(0.1)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        if self.error is not None:
            raise self.error


def live_phases(
    url: str,
    sid: str,
    drive: Callable[[], tuple[list[tuple[str, int]], list[float], float]],
    workers_cpu_s: Callable[[], float],
    pairs: int = PAIRS,
) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, float], dict[str, float]]:
    """``pairs`` quiet and busy phases of ``drive`` (robots streaming: their sessions and
    counts acknowledged, ACK latencies, wall time), ``workers_cpu_s`` the workers' CPU time:
    every latency of each side, every phase's p99 (ms), each side's frames stored per
    second, and each side's CPU use by the workers (cores)."""
    lat: dict[str, list[float]] = {"quiet": [], "busy": []}
    per_phase: dict[str, list[float]] = {"quiet": [], "busy": []}
    frames = {"quiet": 0.0, "busy": 0.0}
    seconds = {"quiet": 0.0, "busy": 0.0}
    cpu = {"quiet": 0.0, "busy": 0.0}
    for _ in range(pairs):
        for side in ("quiet", "busy"):
            busy = _Busy(url, sid).start() if side == "busy" else None
            if busy is not None:
                time.sleep(RAMP_S)
            else:
                wait_idle(workers_cpu_s)
            cpu0 = workers_cpu_s()
            done, latencies, secs = drive()
            cpu[side] += workers_cpu_s() - cpu0
            if busy is not None:
                busy.stop()
            lat[side] += latencies
            per_phase[side].append(p99_ms(latencies))
            frames[side] += sum(a for _, a in done)
            seconds[side] += secs
    rates = {side: frames[side] / seconds[side] for side in frames}
    cores = {side: cpu[side] / seconds[side] for side in cpu}
    return lat, per_phase, rates, cores


def live_results(
    port: int,
    token: str,
    url: str,
    sid: str,
    robots: int,
    fps: float,
    workers: list[int],
) -> list[Result]:
    """The live link's ACK p99 and ingest rate with the ``workers`` (process ids) busy
    against idle."""
    with robots_apart() as robots_priority:
        lat, per_phase, rates, cores = live_phases(
            url,
            sid,
            lambda: drive_robots(port, token, robots, PHASE_S, fps),
            lambda: cpu_s(workers),
        )
    quiet, busy = p99_ms(lat["quiet"]), p99_ms(lat["busy"])
    return [
        {
            "name": "scale.live_ack_p99_with_job",
            "value": busy,
            "unit": "ms",
            "baseline": quiet,
            "baseline_is": "the same robots with the workers idle",
            "ratio": round(busy / quiet, 2),
            "phases": f"{len(per_phase['quiet'])} quiet and {len(per_phase['busy'])} busy of "
            f"{PHASE_S:.0f} s, alternating",
            "busy_phases_p99_ms": per_phase["busy"],
            "quiet_phases_p99_ms": per_phase["quiet"],
            "robots": robots,
            "fps_per_robot": fps,
            "robots_realtime_priority": robots_priority,
            "workers_cores_busy": round(cores["busy"], 2),
            "workers_cores_quiet": round(cores["quiet"], 2),
        },
        {
            "name": "scale.live_frames_per_second_with_job",
            "value": round(rates["busy"], 1),
            "unit": "frames/s",
            "baseline": round(rates["quiet"], 1),
            "ratio": round(rates["busy"] / rates["quiet"], 3),
            "offered": robots * fps,
        },
    ]
