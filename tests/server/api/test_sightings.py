"""The frames each defect of a processed session was seen in, over REST."""

from __future__ import annotations

import math

import httpx

from tests.conftest import LiveServer


def test_each_defect_was_seen_in_the_frames_over_it(inspected: tuple[LiveServer, str]) -> None:
    """The frames a defect is replayed from: those whose footprint holds its centre, with
    the pose and the telemetry of that moment; a frame defect's own frame among them."""
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    mosaic = httpx.get(f"{api}/defects", params={"source": "mosaic"}).json()["data"]
    frame_defect = httpx.get(f"{api}/defects", params={"source": "frame", "limit": 1}).json()
    for d in [d for d in mosaic if not d["drawn_by"]][:3]:
        seen = httpx.get(f"{api}/defects/{d['id']}/sightings").raise_for_status().json()
        assert seen, d  # every mosaic defect lies under some frame
        times = [s["t_s"] for s in seen]
        assert times == sorted(times) and times[0] >= 0
        cx = d["world_x_m"] + d["world_w_m"] / 2
        for s in seen:  # the camera (behind the robot) was within a footprint of the defect
            camera_x = s["pose"]["x"] - 0.12 * math.cos(s["pose"]["yaw"])
            assert abs(camera_x - cx) < 0.2
            assert abs(s["telemetry"]["dt_s"]) < 1.0 and "battery_v" in s["telemetry"]["data"]
            image = httpx.get(live.url + s["image_url"])
            assert image.status_code == 200 and image.content[:2] == b"\xff\xd8"
    fd = frame_defect["data"][0]
    own = httpx.get(f"{api}/defects/{fd['id']}/sightings").json()
    assert fd["frame_seq"] in [s["seq"] for s in own]
    assert httpx.get(f"{api}/defects/999999/sightings").status_code == 404
