"""A structure's history over REST, on the processed inspection and earlier visits of its
structure made from it (known offsets, a crack growing visit by visit, a defect new, one
repaired): the visits oldest first, each defect's track across them, and crops of each
visit's mosaic that show the same ground."""

from __future__ import annotations

import io

import cv2
import httpx
import numpy as np
import pytest
from PIL import Image

from tests.conftest import LiveServer
from tests.server.earlier_visits import (
    REPAIRED_NUMBER,
    add_earlier_visit,
    forget_session,
    stitch_result,
)


def _structure(live: LiveServer, sid: str, name: str) -> int:
    api = f"{live.url}/api"
    st = httpx.post(f"{api}/structures", json={"name": f"{name} {sid[:8]}"}).json()["id"]
    r = httpx.put(f"{api}/sessions/{sid}/structure", json={"structure_id": st})
    assert r.status_code == 200, r.text
    return int(st)


def _png(r: httpx.Response) -> np.ndarray:
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGBA"))


def test_a_structures_visits_and_each_defects_history(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api"
    st = _structure(live, sid, "History")
    assert [v["session_id"] for v in httpx.get(f"{api}/structures/{st}/visits").json()] == [sid]
    alone = httpx.get(f"{api}/structures/{st}/history").json()
    assert all([e["status"] for e in t["entries"]] == ["baseline"] for t in alone["tracks"])
    oldest = add_earlier_visit(live, sid, st, days=1460, shift_m=(0.03, -0.02), shorter_mm=16)
    middle = None
    try:
        middle = add_earlier_visit(
            live, sid, st, days=730, shift_m=(-0.01, 0.02), shorter_mm=8, repaired=False
        )
        visits = httpx.get(f"{api}/structures/{st}/visits").json()
        assert [v["session_id"] for v in visits] == [oldest.id, middle.id, sid]
        assert [v["date"] for v in visits] == sorted(v["date"] for v in visits)
        assert [v["defects"] for v in visits] == [oldest.found, oldest.found - 1, oldest.found]
        assert all(v["mosaic"] for v in visits) and visits[0]["operator"] == "earlier team"
        # each visit placed through the one before: this session's world lies where the
        # oldest visit's robot started
        assert visits[2]["datum"]["x"] == pytest.approx(oldest.shift_m[0], abs=0.002)
        assert visits[2]["datum"]["y"] == pytest.approx(oldest.shift_m[1], abs=0.002)

        history = httpx.get(f"{api}/structures/{st}/history").json()
        assert [v["session_id"] for v in history["visits"]] == [oldest.id, middle.id, sid]
        tracks = history["tracks"]
        assert [t["track_id"] for t in tracks] == list(range(1, len(tracks) + 1))
        by_defect = {e["defect_id"]: t for t in tracks for e in t["entries"] if e["defect_id"]}
        grown = by_defect[oldest.grown_id]
        assert [e["session_id"] for e in grown["entries"]] == [oldest.id, middle.id, sid]
        assert [e["status"] for e in grown["entries"]] == ["baseline", "grown", "grown"]
        lengths = [e["length_mm"] for e in grown["entries"]]
        assert np.diff(lengths) == pytest.approx([8.0, 8.0])
        assert [e["status"] for e in by_defect[oldest.missing_id]["entries"]] == ["new"]
        repaired = next(t for t in tracks if t["entries"][0]["number"] == REPAIRED_NUMBER)
        assert [e["status"] for e in repaired["entries"]] == ["baseline", "gone"]
        assert repaired["entries"][1]["defect_id"] is None
        steady = [t for t in tracks if t not in (grown, repaired, by_defect[oldest.missing_id])]
        assert len(steady) == oldest.found - 2
        for t in steady:
            assert [e["status"] for e in t["entries"]] == ["baseline", "unchanged", "unchanged"]
            assert len({e["number"] for e in t["entries"]}) == 1  # one number on every visit
    finally:  # the session is shared with other tests: the earlier visits go again
        for visit in (oldest, middle):
            if visit is not None:
                forget_session(live, visit.id)
        httpx.put(f"{api}/sessions/{sid}/structure", json={"structure_id": None})


def test_crops_of_two_visits_show_the_same_ground(inspected: tuple[LiveServer, str]) -> None:
    live, sid = inspected
    api = f"{live.url}/api"
    st = _structure(live, sid, "Crops")
    earlier = add_earlier_visit(live, sid, st)
    try:
        changes = httpx.get(f"{api}/sessions/{sid}/changes").json()
        datum = changes["registration"]["datum"]
        stitch = stitch_result(live, sid)
        ppm, (ox, oy) = stitch["px_per_m"], stitch["origin_m"]
        extent = (stitch["width_px"] / ppm, stitch["height_px"] / ppm)

        def inside(c: dict) -> float:  # how far the defect's centre is in from the mosaic's edge
            x0, y0, x1, y1 = c["after"]["box_m"]
            u, v = (x0 + x1) / 2 - datum["x"] - ox, (y0 + y1) / 2 - datum["y"] - oy
            return min(u, extent[0] - u, v, extent[1] - v)

        defect = max((c for c in changes["changes"] if c["after"]), key=inside)
        assert inside(defect) > 0.05
        x0, y0, x1, y1 = defect["after"]["box_m"]
        cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, 0.04
        box = {"x0": cx - half, "y0": cy - half, "x1": cx + half, "y1": cy + half, "size": 160}
        now = _png(httpx.get(f"{api}/sessions/{sid}/mosaic/crop", params=box))
        then = _png(httpx.get(f"{api}/sessions/{earlier.id}/mosaic/crop", params=box))
        side = max(box["x1"] - box["x0"], box["y1"] - box["y0"])
        assert now.shape == then.shape and max(now.shape[:2]) == 160
        assert now[..., 3].min() == 255  # the mosaic covers the box
        # the crop is the mosaic's pixels under the box, placed through the datum
        u0 = round((box["x0"] - datum["x"] - ox) * ppm)
        v0 = round((box["y0"] - datum["y"] - oy) * ppm)
        w, h = round(side * ppm * now.shape[1] / 160), round(side * ppm * now.shape[0] / 160)
        region = httpx.get(f"{api}/sessions/{sid}/results/mosaic.png").content
        full = np.asarray(Image.open(io.BytesIO(region)).convert("RGB"))
        expected = cv2.resize(full[v0 : v0 + h, u0 : u0 + w], now.shape[1::-1], cv2.INTER_AREA)
        assert _ncc(now[..., :3], expected) > 0.95
        # the earlier visit's crop, from its own mosaic, shows the same ground; the box
        # taken without the datum would not
        assert _ncc(now[..., :3], then[..., :3]) > 0.8
        off = {**box, "x0": box["x0"] + 0.03, "x1": box["x1"] + 0.03}
        shifted = _png(httpx.get(f"{api}/sessions/{earlier.id}/mosaic/crop", params=off))
        assert _ncc(now[..., :3], shifted[..., :3]) < _ncc(now[..., :3], then[..., :3]) - 0.1
        # beyond the mosaic: transparent; a box the wrong way round: refused
        away = {"x0": 50, "y0": 50, "x1": 51, "y1": 51}
        assert _png(httpx.get(f"{api}/sessions/{sid}/mosaic/crop", params=away))[..., 3].max() == 0
        flipped = {**box, "x0": box["x1"], "x1": box["x0"]}
        assert httpx.get(f"{api}/sessions/{sid}/mosaic/crop", params=flipped).status_code == 422
    finally:
        forget_session(live, earlier.id)
        httpx.put(f"{api}/sessions/{sid}/structure", json={"structure_id": None})


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation of two images' grey levels."""
    ga = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY).astype(np.float64)
    gb = cv2.cvtColor(np.ascontiguousarray(b), cv2.COLOR_RGB2GRAY).astype(np.float64)
    ga, gb = ga - ga.mean(), gb - gb.mean()
    return float((ga * gb).sum() / np.sqrt((ga**2).sum() * (gb**2).sum()))


def test_unknown_structures_and_sessions_are_not_found(inspected: tuple[LiveServer, str]) -> None:
    live, _ = inspected
    api = f"{live.url}/api"
    assert httpx.get(f"{api}/structures/999999/visits").status_code == 404
    assert httpx.get(f"{api}/structures/999999/history").status_code == 404
    box = {"x0": 0, "y0": 0, "x1": 1, "y1": 1}
    assert httpx.get(f"{api}/sessions/nope/mosaic/crop", params=box).status_code == 404
    empty = httpx.post(f"{api}/structures", json={"name": "Never visited"}).json()["id"]
    assert httpx.get(f"{api}/structures/{empty}/visits").json() == []
    assert httpx.get(f"{api}/structures/{empty}/history").json()["tracks"] == []
