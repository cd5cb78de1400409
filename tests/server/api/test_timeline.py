"""A processed session's timeline over REST: one moment per frame, placed as the coverage
map places it, each defect at the first frame over it, and telemetry series of any field."""

from __future__ import annotations

import uuid

import httpx
import numpy as np

from robot_link.protocol import MessageType, decode_message
from server.reports.timeline import first_sightings, inside_convex
from tests.conftest import LiveServer
from tests.server.helpers import msg, robot_ws, start


def test_moments_agree_with_the_coverage_map_and_the_defects(
    inspected: tuple[LiveServer, str],
) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    tl = httpx.get(f"{api}/timeline").raise_for_status().json()
    frames = httpx.get(f"{api}/frames", params={"limit": 1000}).json()
    assert [m["seq"] for m in tl["frames"]] == [f["seq"] for f in frames["data"]]
    times = [m["t_s"] for m in tl["frames"]]
    assert times == sorted(times) and times[0] >= 0 and tl["duration_s"] == times[-1]
    # the frame, the coverage map and the mosaic cursor show one placement
    coverage = httpx.get(f"{api}/coverage", params={"grid": "false"}).json()
    placed = {f["seq"]: f for f in coverage["frames"]}
    for m in tl["frames"]:
        assert m["footprint"] == placed[m["seq"]]["footprint"]
        assert m["placed_by"] == placed[m["seq"]]["placed_by"]
    assert {m["placed_by"] for m in tl["frames"]} == {"mosaic"}
    # the robot is behind its camera (T_robot_camera), facing the way the frame is turned
    session = httpx.get(api).json()
    offset = session["calibration"]["camera"]["T_robot_camera"]
    for m in tl["frames"]:
        x, y, yaw = m["robot"]
        centre = np.mean(m["footprint"], axis=0)
        cam = np.array([x, y]) + [
            offset[0] * np.cos(yaw) - offset[1] * np.sin(yaw),
            offset[0] * np.sin(yaw) + offset[1] * np.cos(yaw),
        ]
        assert np.allclose(cam, centre, atol=1e-3)
    # each placed defect: inside the footprint of its first frame and of no earlier one
    defects = httpx.get(f"{api}/defects", params={"limit": 5000}).json()["data"]
    assert {d["id"] for d in tl["defects"]} == {d["id"] for d in defects}
    index = {m["seq"]: i for i, m in enumerate(tl["frames"])}
    by_id = {d["id"]: d for d in defects}
    mosaic_seen = 0
    for td in tl["defects"]:
        d = by_id[td["id"]]
        if d["source"] == "frame":
            assert td["first_seq"] == d["frame_seq"]
            continue
        centre = [d["world_x_m"] + d["world_w_m"] / 2, d["world_y_m"] + d["world_h_m"] / 2]
        polys = np.array([m["footprint"] for m in tl["frames"]])
        holds = inside_convex(np.array([centre]), polys)[:, 0]
        if td["first_seq"] is None:
            assert not holds.any()
            continue
        mosaic_seen += 1
        i = index[td["first_seq"]]
        assert holds[i] and not holds[:i].any()
        assert td["t_s"] == tl["frames"][i]["t_s"]
    assert mosaic_seen >= 3
    # telemetry: the robot's fields with the units their keys name
    units = {f["name"]: f["unit"] for f in tl["telemetry"]["fields"]}
    assert units["battery_v.main"] == "V" and units["wheel_speed_mps[0]"] == "m/s"
    assert units["adhesion_margin"] == ""


def test_a_telemetry_series_is_the_samples_values(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    raw = httpx.get(f"{api}/telemetry", params={"limit": 5000}).json()["data"]
    fields = ["battery_v.main", "wheel_speed_mps[1]", "no.such_m"]
    s = httpx.get(f"{api}/telemetry/series", params={"field": fields}).raise_for_status().json()
    assert s["samples"] == len(raw) and s["stride"] == 1
    by_time = sorted(raw, key=lambda r: (r["timestamp"], r["seq"]))
    assert s["timestamps"] == [r["timestamp"] for r in by_time]
    assert s["series"]["battery_v.main"] == [r["data"]["battery_v"]["main"] for r in by_time]
    assert s["series"]["wheel_speed_mps[1]"] == [r["data"]["wheel_speed_mps"][1] for r in by_time]
    assert s["series"]["no.such_m"] == [None] * len(raw)
    assert s["units"] == {"battery_v.main": "V", "wheel_speed_mps[1]": "m/s", "no.such_m": "m"}
    few = httpx.get(f"{api}/telemetry/series", params={"field": fields[:1], "max_points": 10})
    few_body = few.json()
    assert len(few_body["timestamps"]) <= 10 and few_body["stride"] > 1
    assert few_body["timestamps"][0] == by_time[0]["timestamp"]
    for bad in ({"field": []}, {"field": ["x" * 201]}, {"field": ["a"], "max_points": 1}):
        assert httpx.get(f"{api}/telemetry/series", params=bad).status_code == 422
    assert httpx.get(f"{live.url}/api/sessions/nosuch/timeline").status_code == 404


def test_first_sightings_take_the_earliest_footprint_across_blocks() -> None:
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    polys = np.stack([square + [10 * k, 0] for k in range(600)])  # more than one block
    polys[550] = square + [0.5, 0.5]  # holds (1.2, 1.2) first
    polys[580] = square
    points = np.array([[0.5, 0.5], [1.2, 1.2], [5000.0, 0.5], [-3.0, 0.0]])
    first = first_sightings(points, polys)
    assert first.tolist() == [0, 550, 500, -1]
    turned = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], dtype=float)  # the other way round
    assert inside_convex(np.array([[0.5, 0.5], [1.0, 0.5]]), turned[None]).tolist() == [
        [True, True]
    ]


def test_a_field_sent_only_for_a_while_is_listed(live_server: LiveServer) -> None:
    """A robot sends a sweep's progress only while it sweeps, mid-session: the session's
    fields list it, with its unit, and its series holds it there and null elsewhere."""
    sid = uuid.uuid4()
    with robot_ws(live_server) as ws:
        ws.send(start(sid))
        for k in range(600):
            meta: dict = {"battery_v": {"main": 12.5 - k * 1e-3}}
            if 300 <= k < 320:
                meta["sweep"] = {"lanes_done": k - 300, "covered_m2": 0.01 * (k - 300)}
            ws.send(msg(sid, k + 2, MessageType.TELEMETRY, meta))
        for _ in range(601):
            decode_message(ws.recv(timeout=10))
    api = f"{live_server.url}/api/sessions/{sid}"
    units = {f["name"]: f["unit"] for f in httpx.get(f"{api}/telemetry/fields").json()["fields"]}
    assert units == {"battery_v.main": "V", "sweep.lanes_done": "", "sweep.covered_m2": "m²"}
    s = httpx.get(f"{api}/telemetry/series", params={"field": "sweep.lanes_done"}).json()
    values = s["series"]["sweep.lanes_done"]
    assert values[300:320] == list(range(20)) and values[:300] == [None] * 300
