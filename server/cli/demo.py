"""``steelscan demo``: the ground station, a simulated robot over the network, the jobs, a score."""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import signal
import sys
import time
from typing import Any

import httpx
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from processing.metrics import (
    Box,
    absolute_trajectory_error,
    account_defects,
    mosaic_overlap_errors,
)
from processing.poses import parse_tum
from robot_link.client import RobotLink
from robot_link.sim.inspection import InspectionSim, SimConfig, SimResult
from server.api.accounts import create_user
from server.config import Settings
from server.link.robots import create_robot
from server.loopback import BackgroundServer, free_port
from server.storage.db import make_engine, make_sessionmaker, upgrade
from server.storage.models import Role

log = logging.getLogger(__name__)


def world_boxes(defects: list[dict[str, Any]]) -> list[Box]:
    """Boxes on the structure of the defects (REST rows) that have a world position."""
    return [
        Box(d["defect_class"], d["world_x_m"], d["world_y_m"], d["world_w_m"], d["world_h_m"])
        for d in defects
        if d.get("world_x_m") is not None
    ]


def score(
    result: SimResult,
    session: dict[str, Any],
    defects: list[dict[str, Any]],
    trajectory_tum: str | None,
    frame_defects: list[dict[str, Any]] | None = None,
    mosaic_world: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Compare what the station found (on the mosaic, and frame by frame) with the simulator's ground truth."""
    assert result.structure is not None
    truth = [Box(d.defect_class, *d.bbox_m) for d in result.structure.defects]
    found = account_defects(world_boxes(defects), truth)
    out: dict[str, Any] = {
        "defects_found": len(defects),
        "defects_placed": found.found,  # on the structure: the ones scored
        "defects_true": found.true,
        "defects_matched": found.matched,
        "defects_on_true": found.on_true,
        "defects_in_pieces": found.pieces,
        "false_alarms": found.false_alarms,
        "precision": round(found.precision, 3),
        "recall": round(found.recall, 3),
    }
    if frame_defects is not None:
        per_frame = account_defects(world_boxes(frame_defects), truth)
        out["frame_defects_found"] = per_frame.found
        out["frame_defects_matched"] = per_frame.matched
        out["frame_precision"] = round(per_frame.precision, 3)
    out["map_ate_m"] = None
    map_job = next(
        (j for j in session["jobs"] if j["kind"] == "map" and j["state"] == "done"), None
    )
    if trajectory_tum and map_job:
        _, est = parse_tum(trajectory_tum)
        seqs = map_job["result"]["cloud_seqs"]
        gt = np.array([result.cloud_poses_true[s] for s in seqs])
        if len(est) == len(gt):
            out["map_ate_m"] = round(absolute_trajectory_error(est, gt), 4)
            odom = np.array([result.cloud_poses_odom[s] for s in seqs])
            out["odometry_ate_m"] = round(absolute_trajectory_error(odom, gt), 4)
    out.update(_mosaic_scores(result, mosaic_world))
    return out


def _mosaic_scores(result: SimResult, world: dict[str, Any] | None) -> dict[str, Any]:
    """Relative placement error of overlapping frames in the mosaic against the simulator's
    true camera poses (px, worst frame corner)."""
    if (
        not world
        or len(world.get("frames", [])) != len(result.frame_poses_true)
        or not result.frame_poses_true
    ):
        return {}
    est = np.array([[f["x"], f["y"], np.radians(f["theta_deg"])] for f in world["frames"]])
    truth = np.array(result.frame_poses_true, dtype=np.float64)
    truth[:, :2] *= world["px_per_m"]
    errors, _ = mosaic_overlap_errors(est, truth, tuple(result.frame_size))
    if len(errors) == 0:
        return {}
    return {
        "mosaic_overlap_error_px": {
            "mean": round(float(errors.mean()), 3),
            "max": round(float(errors.max()), 3),
            "pairs": len(errors),
        }
    }


def run_demo(
    settings: Settings,
    *,
    port: int = 0,
    exit_when_done: bool = False,
    keep_serving: bool = False,
    time_scale: float = 20.0,
    lanes: int = 5,
    seed: int = 7,
) -> int:
    """Run everything; the last stdout line is the JSON summary when ``exit_when_done``.
    SIGTERM stops it as Ctrl-C does."""
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        return _run_demo(settings, port, exit_when_done, keep_serving, time_scale, lanes, seed)
    except KeyboardInterrupt:
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_demo(
    settings: Settings,
    port: int,
    exit_when_done: bool,
    keep_serving: bool,
    time_scale: float,
    lanes: int,
    seed: int,
) -> int:
    console = Console(stderr=True)
    token, operator, password = _accounts(settings)
    server = BackgroundServer(settings, port or free_port())
    server.start()
    print(f"Dashboard: {server.url}/   (API docs: {server.url}/docs)", flush=True)
    print(f"Operator login: {operator} / {password}", flush=True)
    auth = _login(server.url, operator, password)
    console.print(f"[bold]steelscan demo[/]: data in {settings.data_dir.resolve()}")
    try:
        with Progress(
            TextColumn("{task.description:<28}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%  {task.fields[note]}"),
            TimeElapsedColumn(),
            console=console,
            transient=False,
        ) as progress:
            sim_task = progress.add_task("robot inspection (live)", total=1.0, note="")
            result = asyncio.run(
                _run_sim(
                    server.url,
                    token,
                    SimConfig(seed=seed, lanes=lanes, time_scale=time_scale),
                    lambda f, m: progress.update(sim_task, completed=f, note=m),
                )
            )
            progress.update(
                sim_task,
                completed=1.0,
                note=f"{result.frames_sent} frames, {result.clouds_sent} clouds sent",
            )
            session = _wait_for_jobs(server.url, auth, result.session_id, progress)
        summary = _summary(server.url, auth, result, session)
        shown = httpx.post(
            f"{server.url}/api/sessions/{result.session_id}/view3d", headers=auth, timeout=60
        )
        if shown.status_code == 200:
            console.print(
                f"3D view of the session: {server.url}/viser/ (open it from the dashboard's session page)"
            )
    except BaseException:
        server.stop()
        raise
    print(json.dumps(summary), flush=True)
    if exit_when_done and not keep_serving:
        server.stop()
        return 0
    _serve_with_a_robot_to_drive(server, token, seed, console)
    return 0


def _accounts(settings: Settings) -> tuple[str, str, str]:
    """A new robot's token and an operator's name and password, in the station's database."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    url_db = settings.resolved_database_url()
    upgrade(url_db)
    engine = make_engine(url_db)
    factory = make_sessionmaker(engine)
    token = create_robot(factory, f"sim-{int(time.time() * 1000)}")
    operator, password = f"operator-{secrets.token_hex(2)}", secrets.token_urlsafe(12)
    create_user(factory, operator, password, Role.operator)
    engine.dispose()
    return token, operator, password


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM ends the demo as Ctrl-C does: the robot's session ends, the station stops
    its workers and closes its files."""
    raise KeyboardInterrupt


def _serve_with_a_robot_to_drive(
    server: BackgroundServer, token: str, seed: int, console: Console
) -> None:
    """Keep serving, with a second robot the user drives from the dashboard's Drive page
    (live video, dead-man stop), until Ctrl-C."""
    from robot_link.sim.teleop import start_teleop_robot

    teleop = None
    try:
        teleop = start_teleop_robot(server.url, token, seed=seed)
        console.print(
            f"Serving {server.url}/ — drive the simulated robot on the Drive page (arrows/WASD), "
            f"review the inspection under Sessions. Ctrl-C stops."
        )
        while server.thread.is_alive():
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    if teleop is not None:
        teleop.sim.end_requested = True
        teleop.thread.join(timeout=10)
    server.stop()


async def _run_sim(url: str, token: str, config: SimConfig, progress: Any) -> SimResult:
    link = RobotLink(url, token)
    await link.start()
    try:
        return await InspectionSim(link, config, progress=progress).run()
    finally:
        await link.close()


def _login(url: str, name: str, password: str) -> dict[str, str]:
    """Authorization header of a fresh bearer token."""
    r = httpx.post(
        f"{url}/api/auth/token", data={"username": name, "password": password}, timeout=30
    )
    return {"Authorization": f"Bearer {r.raise_for_status().json()['access_token']}"}


def _wait_for_jobs(
    url: str, auth: dict[str, str], session_id: str, progress: Progress, timeout_s: float = 600
) -> dict[str, Any]:
    tasks: dict[int, Any] = {}
    deadline = time.monotonic() + timeout_s
    with httpx.Client(base_url=url, timeout=30, headers=auth) as client:
        while True:
            session = client.get(f"/api/sessions/{session_id}").raise_for_status().json()
            for job in session["jobs"]:
                if job["id"] not in tasks:
                    tasks[job["id"]] = progress.add_task(
                        f"job: {job['kind']}", total=1.0, note="queued"
                    )
                note = job["error"] or job["message"] or job["state"]
                progress.update(
                    tasks[job["id"]],
                    completed=job["progress"] if job["state"] != "done" else 1.0,
                    note=note[:60],
                )
            if session["jobs"] and all(j["state"] in ("done", "failed") for j in session["jobs"]):
                return session
            if time.monotonic() > deadline:
                raise TimeoutError("processing jobs did not finish in time")
            time.sleep(0.5)


def _summary(
    url: str, auth: dict[str, str], result: SimResult, session: dict[str, Any]
) -> dict[str, Any]:
    sid = result.session_id
    with httpx.Client(base_url=url, timeout=30, headers=auth) as client:
        defects = (
            client.get(f"/api/sessions/{sid}/defects", params={"limit": 5000, "source": "mosaic"})
            .raise_for_status()
            .json()["data"]
        )
        frame_defects = (
            client.get(f"/api/sessions/{sid}/defects", params={"limit": 5000, "source": "frame"})
            .raise_for_status()
            .json()["data"]
        )
        traj = client.get(f"/api/sessions/{sid}/results/trajectory.tum")
        world = client.get(f"/api/sessions/{sid}/results/mosaic.json")
    jobs = {j["kind"]: j for j in session["jobs"]}
    mosaic = jobs.get("stitch", {}).get("result", {}).get("mosaic_path")
    map_path = jobs.get("map", {}).get("result", {}).get("map_path")
    summary: dict[str, Any] = {
        "session_id": sid,
        "frames": session["frames"],
        "clouds": session["clouds"],
        "frames_sent": result.frames_sent,
        "clouds_sent": result.clouds_sent,
        "mosaic_path": mosaic,
        "map_path": map_path,
        **score(
            result,
            session,
            defects,
            traj.text if traj.status_code == 200 else None,
            frame_defects,
            world.json() if world.status_code == 200 else None,
        ),
        "jobs": {k: j["state"] for k, j in jobs.items()},
        "job_errors": {k: j["error"] for k, j in jobs.items() if j["error"]},
        "dashboard_url": f"{url}/",
        "report_json_url": f"{url}/api/sessions/{sid}/report.json",
        "report_pdf_url": f"{url}/api/sessions/{sid}/report.pdf",
        "report_csv_url": f"{url}/api/sessions/{sid}/defects.csv",
        "mcap_url": f"{url}/api/sessions/{sid}/export.mcap",
        "mcap_path": jobs.get("export", {}).get("result", {}).get("mcap_path"),
    }
    if any(j["state"] == "failed" for j in jobs.values()):
        print(f"warning: some jobs failed: {summary['job_errors']}", file=sys.stderr)
    return summary
