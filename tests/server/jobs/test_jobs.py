"""Jobs through REST on the real server: failures are recorded, the server carries on."""

import uuid

import cv2
import httpx
import numpy as np
from sqlalchemy import select
from websockets.sync.client import connect

from robot_link.protocol import MessageType, decode_message
from tests.conftest import LiveServer
from tests.media import undecodable_jpeg
from tests.server.helpers import empty_session, msg, start, wait_job, ws_url


def test_a_failing_job_is_marked_failed_with_its_reason(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        # a sound header, no image data: stored, and the stitcher must say it cannot use it
        ws.send(
            msg(sid, 2, MessageType.FRAME, {"width": 64, "height": 48}, undecodable_jpeg(64, 48))
        )
        for _ in range(2):
            decode_message(ws.recv(timeout=10))
    url = live_server.url
    created = httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "map"})
    assert created.status_code == 202
    job = wait_job(url, created.json()["id"])
    assert job["state"] == "failed" and "no ToF clouds" in job["error"]
    job = wait_job(
        url, httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "stitch"}).json()["id"]
    )
    assert job["state"] == "failed" and "could be read" in job["error"]
    detect = wait_job(
        url, httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "detect"}).json()["id"]
    )
    assert detect["state"] == "failed" and "depends on failed" in detect["error"]
    assert httpx.get(f"{url}/api/health").json()["status"] == "ok"
    jobs = httpx.get(f"{url}/api/sessions/{sid}/jobs").json()
    assert [j["kind"] for j in jobs] == ["map", "stitch", "detect"]


def test_unknown_job_kind_is_a_422(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(start(sid))
        decode_message(ws.recv(timeout=10))
    r = httpx.post(f"{live_server.url}/api/sessions/{sid}/jobs", json={"kind": "teleport"})
    assert r.status_code == 422


def test_stitch_job_serves_a_deep_zoom_pyramid_of_the_session(live_server: LiveServer) -> None:
    from tests.processing.helpers import sweep

    s = sweep(frames=6, pattern="straight", seed=21)
    sid = uuid.uuid4()
    calib = {"camera": {"px_per_m": 1000.0, "T_robot_camera": [0.0, 0.0, 0.0]}}
    with connect(
        ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}
    ) as ws:
        ws.send(
            msg(
                sid,
                1,
                MessageType.SESSION_START,
                {"structure": "plate", "operator": "t", "calibration": calib},
            )
        )
        for k, (jpeg, p) in enumerate(zip(s.frames, s.odometry), 2):
            pose = {"x": p[0] / 1000, "y": p[1] / 1000, "yaw": p[2]}
            ws.send(
                msg(sid, k, MessageType.FRAME, {"width": 320, "height": 240, "pose": pose}, jpeg)
            )
        pose = {"x": pose["x"] + 0.01, "y": pose["y"], "yaw": pose["yaw"]}
        corrupt = undecodable_jpeg(320, 240)
        ws.send(
            msg(sid, 8, MessageType.FRAME, {"width": 320, "height": 240, "pose": pose}, corrupt)
        )
        for _ in range(8):
            assert decode_message(ws.recv(timeout=10)).type is MessageType.ACK
    url = f"{live_server.url}/api/sessions/{sid}"
    job = wait_job(live_server.url, httpx.post(f"{url}/jobs", json={"kind": "stitch"}).json()["id"])
    assert job["state"] == "done", job
    assert job["result"]["world_referenced"] and job["result"]["low_confidence_frames"] == 0
    assert job["result"]["skipped_frames"] == [8]  # one unreadable frame fails only itself
    notes = httpx.get(f"{url}/report.json").json()["notes"]
    assert any("Frames left out of the mosaic" in n and ": 1 (seq 8)" in n for n in notes), notes
    dzi = httpx.get(f"{url}/results/mosaic.dzi")
    assert dzi.status_code == 200 and f'Width="{job["result"]["width_px"]}"' in dzi.text
    top = int(np.ceil(np.log2(max(job["result"]["width_px"], job["result"]["height_px"]))))
    tile = httpx.get(f"{url}/mosaic_files/{top}/0_0.jpg")
    assert tile.status_code == 200 and tile.headers["content-type"] == "image/jpeg"
    assert cv2.imdecode(np.frombuffer(tile.content, np.uint8), cv2.IMREAD_COLOR).shape[:2] == (
        255,
        255,
    )
    assert httpx.get(f"{url}/mosaic_files/{top}/99_99.jpg").status_code == 404
    assert httpx.get(f"{url}/mosaic_files/..%2F..%2Fmosaic/0_0.jpg").status_code in (404, 422)
    world = httpx.get(f"{url}/results/mosaic.json").json()
    assert [f["frame"] for f in world["frames"]] == list(range(2, 8))


def test_map_job_on_tof_clouds_alone_beats_the_odometry(live_server: LiveServer) -> None:
    """A session with ToF clouds and odometry but no camera frames: the map job registers
    the organised depth images (pose graph, loop closure at the return) and its trajectory
    is closer to the truth than the odometry it was given."""
    from processing.metrics import absolute_trajectory_error
    from processing.poses import parse_tum
    from robot_link.clouds import encode_depth_png
    from robot_link.sim.sensors import tof_mount
    from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

    sweep = tof_sweep(TofSweepConfig(seed=23))
    mount = tof_mount()
    h, w = int(sweep.intrinsics["height"]), int(sweep.intrinsics["width"])
    sid = uuid.uuid4()
    with connect(
        ws_url(live_server),
        additional_headers={"Authorization": f"Bearer {live_server.token}"},
        max_size=2**22,
    ) as ws:
        ws.send(
            msg(
                sid,
                1,
                MessageType.SESSION_START,
                {
                    "structure": "girder",
                    "calibration": {"tof": {**sweep.intrinsics, "T_robot_tof": mount.tolist()}},
                },
            )
        )
        for k, (cloud, T) in enumerate(zip(sweep.clouds, sweep.odometry)):
            robot = T @ np.linalg.inv(mount)
            pose = {
                "x": float(robot[0, 3]),
                "y": float(robot[1, 3]),
                "yaw": float(np.arctan2(robot[1, 0], robot[0, 0])),
            }
            ws.send(
                msg(
                    sid,
                    k + 2,
                    MessageType.CLOUD,
                    {"encoding": "png16_depth_mm", **sweep.intrinsics, "pose": pose},
                    encode_depth_png(cloud[:, 2].reshape(h, w)),
                )
            )
        for _ in range(len(sweep.clouds) + 1):
            assert decode_message(ws.recv(timeout=10)).type is MessageType.ACK
    url = live_server.url
    job = wait_job(
        url, httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "map"}).json()["id"]
    )
    assert job["state"] == "done", job
    result = job["result"]
    # those that saw nothing: skipped, listed
    assert result["clouds"] + len(result["skipped_clouds"]) == len(sweep.clouds)
    assert not result["guided_by_mosaic"] and result["loop_closures"] >= 1
    assert 0 < result["clouds_with_unobservable_directions"] <= result["clouds"]  # said, not hidden
    _, poses = parse_tum(
        httpx.get(f"{url}/api/sessions/{sid}/results/trajectory.tum").raise_for_status().text
    )
    kept = np.array(result["cloud_seqs"]) - 2
    ate = absolute_trajectory_error(poses, sweep.truth[kept])
    assert ate < 0.75 * absolute_trajectory_error(sweep.odometry[kept], sweep.truth[kept])


def test_a_job_the_station_died_in_runs_again_on_restart_and_fails_after_three(settings) -> None:  # type: ignore[no-untyped-def]
    from server.loopback import BackgroundServer, free_port
    from server.storage.db import make_engine, make_sessionmaker
    from server.storage.models import InspectionSession, Job, JobState
    from tests.conftest import make_token

    make_token(settings)  # creates the database
    engine = make_engine(settings.resolved_database_url())
    with make_sessionmaker(engine)() as db:
        db.add(InspectionSession(id=str(uuid.uuid4()), structure="killed mid-job"))
        db.flush()
        sid = db.scalars(select(InspectionSession.id)).one()
        running = Job(session_id=sid, kind="stitch", state=JobState.running, attempt=1)
        poison = Job(session_id=sid, kind="map", state=JobState.running, attempt=3)
        db.add_all([running, poison])
        db.commit()
        job_id, poison_id = running.id, poison.id
    engine.dispose()
    server = BackgroundServer(settings, free_port())
    server.start()
    try:
        job = wait_job(server.url, job_id)  # ran again: an empty session has no frames
        assert job["attempt"] == 2 and "no camera frames" in job["error"], job
        job = httpx.get(f"{server.url}/api/jobs/{poison_id}").raise_for_status().json()
        assert job["state"] == "failed" and "interrupted 3 times" in job["error"]
    finally:
        server.stop()


def test_a_cancelled_job_never_runs_and_what_needs_it_fails(live_server: LiveServer) -> None:

    sid = empty_session(live_server)
    url = live_server.url
    jobs = [  # one worker: the second waits behind the first
        httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": kind}).json()["id"]
        for kind in ("map", "stitch", "detect")
    ]
    r = httpx.post(f"{url}/api/jobs/{jobs[1]}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "cancelled", r.text
    assert "cancelled by" in r.json()["error"]
    assert httpx.post(f"{url}/api/jobs/{jobs[1]}/cancel").status_code == 409
    assert httpx.post(f"{url}/api/jobs/999999/cancel").status_code == 404
    assert wait_job(url, jobs[0])["state"] == "failed"  # no clouds: it ran, and failed
    detect = wait_job(url, jobs[2])
    assert detect["state"] == "failed" and "cancelled" in detect["error"]
    stitch = httpx.get(f"{url}/api/jobs/{jobs[1]}").json()
    assert stitch["state"] == "cancelled" and stitch["started_at"] is None
