"""The station keeps each live session's trajectory and the defects seen in its frames, and
a browser that connects during the session gets them first thing."""

from __future__ import annotations

import json

from server.live.coverage_state import MAX_TRAIL_POINTS, LiveCoverage
from server.live.events import FrameDefects, Session, Telemetry
from server.live.hub import LiveHub

CRACK = {"defect_class": "crack", "world_box": [0.5, 0.2, 0.04, 0.01], "length_mm": 41.0}


def greeting(hub: LiveHub) -> list[dict]:  # type: ignore[type-arg]
    watcher = hub.watch("ada")
    items = []
    while not watcher.queue.empty():
        items.append(json.loads(watcher.queue.get_nowait()))
    return items


def test_a_browser_connecting_mid_session_gets_the_trajectory_and_defects_so_far() -> None:
    hub = LiveHub(queue_size=2)  # the greeting is kept whole whatever the queue's size
    for i in range(5):
        hub.publish(Telemetry(session_id="s1", data={"pose": {"x": 0.1 * i, "y": 0.2, "yaw": 0}}))
    hub.publish(Telemetry(session_id="s1", data={"pose": {"x": 0.401, "y": 0.2, "yaw": 0}}))
    hub.publish(FrameDefects(session_id="s1", seq=7, defects=[CRACK]))
    hub.publish(Telemetry(session_id="s2", data={"battery_v": 12.1}))  # no pose: no trail
    events = greeting(hub)
    assert events[0]["type"] == "hello"
    [state] = [e for e in events if e["type"] == "coverage_state"]
    assert state["session_id"] == "s1"
    assert state["trail"] == [[0.1 * i, 0.2] for i in range(5)]  # 1 mm on: not a new point
    assert state["found"] == [{"seq": 7, **CRACK}]
    # every browser gets it, a second tab as the first
    assert [e for e in greeting(hub) if e["type"] == "coverage_state"] == [state]
    hub.publish(Session(session_id="s1", event="session_end", robot="r"))
    assert [e for e in greeting(hub) if e["type"] == "coverage_state"] == []


def test_a_long_trajectory_is_thinned_keeping_its_ends() -> None:
    coverage = LiveCoverage()
    for i in range(MAX_TRAIL_POINTS + 1):
        coverage.add_pose("s", {"x": 0.01 * i, "y": 0.0})
    trail = coverage.sessions["s"].trail
    assert len(trail) <= MAX_TRAIL_POINTS // 2 + 2
    assert trail[0] == (0.0, 0.0) and trail[-1] == (0.01 * MAX_TRAIL_POINTS, 0.0)
    coverage.add_pose("s", {"x": float("nan"), "y": 0.0})
    coverage.add_pose("s", {"y": 0.0})
    assert coverage.sessions["s"].trail[-1] == (0.01 * MAX_TRAIL_POINTS, 0.0)
