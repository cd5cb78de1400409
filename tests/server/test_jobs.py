"""Jobs through REST on the real server: failures are recorded, the server carries on."""

import time
import uuid

import httpx
from websockets.sync.client import connect

from robot_link.protocol import decode_message
from tests.conftest import LiveServer
from tests.server.test_ingest import frame, start, ws_url


def wait_job(url: str, job_id: int, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = httpx.get(f"{url}/api/jobs/{job_id}").raise_for_status().json()
        if job["state"] in ("done", "failed"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish")


def test_a_failing_job_is_marked_failed_with_its_reason(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}) as ws:
        ws.send(start(sid))
        ws.send(frame(sid, 2))  # not a decodable image: the stitcher must say so
        for _ in range(2):
            decode_message(ws.recv(timeout=10))
    url = live_server.url
    created = httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "map"})
    assert created.status_code == 202
    job = wait_job(url, created.json()["id"])
    assert job["state"] == "failed" and "no ToF clouds" in job["error"]
    job = wait_job(url, httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "stitch"}).json()["id"])
    assert job["state"] == "failed" and "could be read" in job["error"]
    detect = wait_job(url, httpx.post(f"{url}/api/sessions/{sid}/jobs", json={"kind": "detect"}).json()["id"])
    assert detect["state"] == "failed" and "depends on failed" in detect["error"]
    assert httpx.get(f"{url}/api/health").json() == {"status": "ok"}
    jobs = httpx.get(f"{url}/api/sessions/{sid}/jobs").json()
    assert [j["kind"] for j in jobs] == ["map", "stitch", "detect"]


def test_unknown_job_kind_is_a_422(live_server: LiveServer) -> None:
    sid = uuid.uuid4()
    with connect(ws_url(live_server), additional_headers={"Authorization": f"Bearer {live_server.token}"}) as ws:
        ws.send(start(sid))
        decode_message(ws.recv(timeout=10))
    r = httpx.post(f"{live_server.url}/api/sessions/{sid}/jobs", json={"kind": "teleport"})
    assert r.status_code == 422
