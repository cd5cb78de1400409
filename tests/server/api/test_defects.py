"""Defects drawn by hand on a processed session's mosaic, over REST."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import LiveServer
from tests.server.helpers import wait_job


def test_a_defect_drawn_by_hand_is_numbered_placed_and_kept(
    inspected: tuple[LiveServer, str],
) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    world = httpx.get(f"{api}/results/mosaic.json").json()
    box = {"bbox_x": 40, "bbox_y": 30, "bbox_w": 250, "bbox_h": 20}
    r = httpx.post(f"{api}/defects", json={"defect_class": "crack", **box, "comment": "missed"})
    assert r.status_code == 201, r.text
    drawn = r.json()
    before = httpx.get(f"{api}/defects", params={"source": "mosaic", "limit": 1000}).json()
    assert drawn["number"] == max(d["number"] for d in before["data"])
    assert drawn["drawn_by"] == "anonymous" and drawn["review_status"] == "confirmed"
    ppm = world["px_per_m"]
    assert drawn["length_mm"] == pytest.approx(250 / ppm * 1000)
    assert drawn["world_x_m"] == pytest.approx(world["origin_m"][0] + 40 / ppm)
    # boxes off the mosaic and unknown classes are refused
    off = {**box, "bbox_x": world["width_px"] - 10}
    assert httpx.post(f"{api}/defects", json={"defect_class": "crack", **off}).status_code == 409
    assert httpx.post(f"{api}/defects", json={"defect_class": "dent", **box}).status_code == 422
    # detection runs again: the drawn defect stays, numbers stay one per defect
    job = wait_job(live.url, httpx.post(f"{api}/jobs", json={"kind": "detect"}).json()["id"])
    assert job["state"] == "done"
    after = httpx.get(f"{api}/defects", params={"source": "mosaic", "limit": 1000}).json()["data"]
    kept = [d for d in after if d["drawn_by"]]
    assert [d["comment"] for d in kept] == ["missed"]
    assert sorted(d["number"] for d in after) == list(range(1, len(after) + 1))
