"""Jobs on Celery workers against real services: PostgreSQL, Redis, the station and
``steelscan worker`` processes sharing one data directory. A worker killed mid-job costs
time, never a result; a job completes once; cancelling stops it wherever it runs."""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from bench.services import start_worker, stop_workers
from robot_link.protocol import MessageType, decode_message
from server.config import Settings
from server.jobs.priority import cpu_cgroup
from server.jobs.queue import limit_threads
from server.loopback import BackgroundServer, free_port
from tests.conftest import make_token
from tests.server.helpers import msg, wait_job, ws_url

pytestmark = pytest.mark.slow  # real services and worker processes
LEASE_S = 3.0


@dataclass
class Cluster:
    url: str
    token: str
    settings: Settings
    workers: list[subprocess.Popen]
    logs: list[Path]

    def start_worker(self) -> None:
        env = {
            **os.environ,
            "STEELSCAN_DATA_DIR": str(self.settings.data_dir),
            "STEELSCAN_DATABASE_URL": self.settings.resolved_database_url(),
            "STEELSCAN_BROKER_URL": self.settings.broker_url,
            "STEELSCAN_JOB_LEASE_S": str(LEASE_S),
        }
        log = self.settings.data_dir.parent / f"worker{len(self.workers)}.log"
        self.workers.append(start_worker(env, log))
        self.logs.append(log)

    def holder(self, worker: str) -> int:
        """Index of the worker whose process (group) runs an attempt ("name:pid")."""
        pid = int(worker.rsplit(":", 1)[1])
        for i, w in enumerate(self.workers):
            if os.getpgid(pid) == w.pid:
                return i
        raise AssertionError(f"no worker of ours runs {worker}")


@pytest.fixture
def cluster(tmp_path: Path, postgres, redis_server) -> Iterator[Cluster]:  # type: ignore[no-untyped-def]
    settings = Settings(
        data_dir=tmp_path / "data",
        database_url=postgres.new_database(),
        job_backend="celery",
        broker_url=redis_server.url,
        job_lease_s=LEASE_S,
        auto_process=False,
        view3d=False,
        live_map=False,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    c = Cluster(server.url, token, settings, [], [])
    try:
        c.start_worker()
        c.start_worker()
        yield c
    finally:
        stop_workers(c.workers, grace_s=20)
        server.stop()


def record(c: Cluster, frames: int) -> str:
    """A session of ``frames`` camera frames of a lawn-mower sweep over a cracked plate."""
    from tests.processing.helpers import sweep

    s = sweep(frames=frames, seed=31, cracked=True)
    sid = uuid.uuid4()
    calib = {"camera": {"px_per_m": 1000.0, "T_robot_camera": [0.0, 0.0, 0.0]}}
    with connect(ws_url(c), additional_headers={"Authorization": f"Bearer {c.token}"}) as ws:  # type: ignore[arg-type]
        start = {"structure": "plate", "operator": "t", "calibration": calib}
        ws.send(msg(sid, 1, MessageType.SESSION_START, start))
        for k, (jpeg, p) in enumerate(zip(s.frames, s.odometry), 2):
            pose = {"x": p[0] / 1000, "y": p[1] / 1000, "yaw": p[2]}
            meta = {"width": 320, "height": 240, "pose": pose}
            ws.send(msg(sid, k, MessageType.FRAME, meta, jpeg))
        for _ in range(frames + 1):
            assert decode_message(ws.recv(timeout=10)).type is MessageType.ACK
    return str(sid)


def start_job(c: Cluster, sid: str, kind: str) -> int:
    r = httpx.post(f"{c.url}/api/sessions/{sid}/jobs", json={"kind": kind})
    assert r.status_code == 202, r.text
    return int(r.json()["id"])


def wait_running(c: Cluster, job_id: int, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = httpx.get(f"{c.url}/api/jobs/{job_id}").json()
        if job["state"] == "running" and job["worker"]:
            return job
        assert job["state"] == "queued", job
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} never started")


def _results(url: str, data_dir: Path, sid: str) -> tuple[np.ndarray, list[tuple]]:
    """A processed session's mosaic (pixels) and defects (class, box, area, source)."""
    mosaic = cv2.imread(str(data_dir / "sessions" / sid / "results" / "mosaic.png"))
    assert mosaic is not None
    rows = httpx.get(f"{url}/api/sessions/{sid}/defects", params={"limit": 5000}).json()["data"]
    keys = (
        "source",
        "frame_seq",
        "defect_class",
        "bbox_x",
        "bbox_y",
        "bbox_w",
        "bbox_h",
        "area_px",
    )
    return mosaic, sorted(tuple(d[k] for k in keys) for d in rows)


def embedded_results(tmp_path: Path, frames: int) -> tuple[np.ndarray, list[tuple]]:
    """The same recording processed by a station's own worker processes (SQLite)."""
    settings = Settings(
        data_dir=tmp_path / "embedded",
        database_url=f"sqlite:///{tmp_path / 'embedded' / 'steelscan.db'}",
        auto_process=False,
        view3d=False,
        live_map=False,
    )
    token = make_token(settings)
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        here = Cluster(server.url, token, settings, [], [])
        sid = record(here, frames)
        for kind in ("stitch", "detect"):
            assert wait_job(server.url, start_job(here, sid, kind))["state"] == "done"
        return _results(server.url, settings.data_dir, sid)
    finally:
        server.stop()


def test_jobs_run_on_workers_and_share_one_jobs_parts(cluster: Cluster, tmp_path: Path) -> None:
    sid = record(cluster, 60)
    stitch_id = start_job(cluster, sid, "stitch")
    stitch = wait_job(cluster.url, stitch_id)
    assert stitch["state"] == "done", stitch
    assert stitch["attempt"] == 1 and stitch["worker"].startswith("steelscan-")
    seconds = stitch["result"]["seconds"]
    assert stitch["result"]["pairs"] > 59 and set(seconds) == {
        "pairs",
        "registrations",  # spread over the workers on a job queue, as are the bands
        "bands",
        "render",
    }
    assert 0 < seconds["registrations"] < seconds["pairs"]
    assert 0 < seconds["bands"] < seconds["render"]
    detect_id = start_job(cluster, sid, "detect")
    wait_running(cluster, detect_id)
    seen = set()  # the progress the workers report, as the dashboard reads it
    while (detect := httpx.get(f"{cluster.url}/api/jobs/{detect_id}").json())["state"] == "running":
        seen.add((detect["progress"], detect["message"]))
        time.sleep(0.02)
    assert detect["state"] == "done", detect
    assert any(0 < p < 1 and m for p, m in seen), seen
    defects = httpx.get(f"{cluster.url}/api/sessions/{sid}/defects").json()["data"]
    frame_rows = [d for d in defects if d["source"] == "frame"]
    assert len(frame_rows) == detect["result"]["frame_defects"]  # every part's rows, once
    assert detect["result"]["frame_defects"] > 0
    # the same recording gives the same results in a station's own processes: the mosaic
    # to the pixel, the same defects
    mosaic, found = _results(cluster.url, cluster.settings.data_dir, sid)
    here_mosaic, here_found = embedded_results(tmp_path, 60)
    assert mosaic.shape == here_mosaic.shape and np.array_equal(mosaic, here_mosaic)
    assert found == here_found
    # the frames were spread: both workers did parts of the one job
    for job in (stitch, detect):  # the pairs of the one, the frames of the other
        helped = [
            sum(int(line.split(": ")[-1].split()[0]) for line in log.read_text().splitlines()
                if f"job {job['id']}: " in line and "parts of" in line)
            for log in cluster.logs
        ]  # fmt: skip
        holder = cluster.holder(job["worker"])
        assert helped[1 - holder] > 0, (helped, [p.read_text()[-2000:] for p in cluster.logs])
    # every process of a worker yields the CPU to a station on the same machine: the job
    # processes and the worker's own (broker, pool, results)
    for w in cluster.workers:
        group = [int(p) for p in os.listdir("/proc") if p.isdigit() and _group_of(int(p)) == w.pid]
        assert w.pid in group and len(group) >= 2, group
        assert {os.sched_getscheduler(p) for p in group} == {os.SCHED_IDLE}, group
        # its CPU group yields: an idle cgroup where it may join one, else its session's group
        cpu_groups = {_cpu_cgroup_of(p) for p in group}
        if cpu_groups != {None}:
            assert len(cpu_groups) == 1, cpu_groups
            assert (cpu_groups.pop() / "cpu.idle").read_text().strip() == "1"
        else:
            autogroup = Path(f"/proc/{w.pid}/autogroup")  # a session of its own
            if autogroup.exists():
                assert autogroup.read_text().split()[-1] == "19", autogroup.read_text()


def _cpu_cgroup_of(pid: int) -> Path | None:
    """The CPU cgroup folder of process ``pid`` where it is an idle group, else None."""
    try:
        here = cpu_cgroup(Path(f"/proc/{pid}/cgroup").read_text())
        return here if here and (here / "cpu.idle").read_text().strip() == "1" else None
    except OSError:
        return None


def _group_of(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except ProcessLookupError:
        return None


@pytest.mark.parametrize("what", ["process", "worker"])
def test_a_worker_killed_mid_job_costs_time_not_the_result(cluster: Cluster, what: str) -> None:
    """``process``: the job's process dies (the worker puts the task back); ``worker``: the
    whole worker with its broker connection (the station hands the job out again once its
    lease has run out). Either way another attempt completes it, once."""
    sid = record(cluster, 120)
    assert wait_job(cluster.url, start_job(cluster, sid, "stitch"))["state"] == "done"
    job_id = start_job(cluster, sid, "detect")
    running = wait_running(cluster, job_id)
    holder = cluster.holder(running["worker"])
    if what == "process":
        os.kill(int(running["worker"].rsplit(":", 1)[1]), signal.SIGKILL)
    else:
        os.killpg(cluster.workers[holder].pid, signal.SIGKILL)
    job = wait_job(cluster.url, job_id, timeout_s=120)
    assert job["state"] == "done", job
    assert job["attempt"] >= 2 and job["worker"] != running["worker"]
    defects = httpx.get(f"{cluster.url}/api/sessions/{sid}/defects").json()["data"]
    assert sum(d["source"] == "frame" for d in defects) == job["result"]["frame_defects"]
    assert sum(d["source"] == "mosaic" for d in defects) == job["result"]["defects"]


def test_cancelling_stops_a_running_job_and_what_needs_it(cluster: Cluster) -> None:
    sid = record(cluster, 120)
    stitch_id = start_job(cluster, sid, "stitch")
    wait_running(cluster, stitch_id)
    detect_id = start_job(cluster, sid, "detect")  # waits for the stitch
    r = httpx.post(f"{cluster.url}/api/jobs/{stitch_id}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    assert httpx.post(f"{cluster.url}/api/jobs/{stitch_id}/cancel").status_code == 409
    detect = wait_job(cluster.url, detect_id)
    assert detect["state"] == "failed" and "cancelled" in detect["error"]
    time.sleep(2 * LEASE_S)  # the attempt notices at its next beat and its result is dropped
    stitch = httpx.get(f"{cluster.url}/api/jobs/{stitch_id}").json()
    assert stitch["state"] == "cancelled" and stitch["result"] == {}


def _icp_cores(queue: Any) -> None:
    """In a fresh process limited as a worker process is: Open3D's thread limit, and the
    cores an ICP of 100,000 points kept busy (CPU time over wall time)."""
    import numpy as np
    import open3d as o3d

    limit_threads(1)
    reg = o3d.pipelines.registration
    pts = np.random.default_rng(3).random((100_000, 3))
    a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts + 0.001))
    b.estimate_normals()
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(3):
        reg.registration_icp(a, b, 0.05, np.eye(4), reg.TransformationEstimationPointToPlane())
    cores = (time.process_time() - cpu) / (time.perf_counter() - wall)
    queue.put((o3d.utility.get_max_threads(), cores))


def test_a_worker_process_keeps_open3d_to_its_threads() -> None:
    """A worker process is one core's worth of work (``STEELSCAN_WORKER_THREADS``): Open3D's
    oneTBB pool, which no environment variable bounds, would take every core for an ICP."""
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_icp_cores, args=(queue,))
    proc.start()
    threads, cores = queue.get(timeout=120)
    proc.join(30)
    assert threads == 1
    assert cores < 1.3
