"""Which defects the report lists and how it marks them, in defects.csv and defects.json."""

from __future__ import annotations

import csv
import io

import httpx
from sqlalchemy import delete

from server.storage.db import make_engine, make_sessionmaker
from server.storage.models import Defect, InspectionSession
from tests.conftest import LiveServer


def _tiny_detections(live: LiveServer, sid: str) -> list[int]:
    """A crack one pixel long and a corrosion patch of no area, as detection stores them."""
    engine = make_engine(live.settings.resolved_database_url())
    try:
        with make_sessionmaker(engine)() as db:
            s = db.get(InspectionSession, sid)
            assert s is not None
            mm_per_px = 1000.0 / float(s.calibration["camera"]["px_per_m"])
            common = dict(
                session_id=sid, source="mosaic", bbox_x=5, bbox_y=5, bbox_w=1, bbox_h=1,
                area_px=1, length_px=1.0, max_width_px=1.0, mean_width_px=1.0,
                orientation_deg=0.0, world_x_m=0.0, world_y_m=0.0, world_w_m=0.0,
                world_h_m=0.0,
            )  # fmt: skip
            rows = [
                Defect(number=9001, defect_class="crack", length_mm=mm_per_px, **common),
                Defect(number=9002, defect_class="corrosion", area_mm2=0.0, **common),
            ]
            db.add_all(rows)
            db.commit()
            return [d.id for d in rows]
    finally:
        engine.dispose()


def _drawn_by(live: LiveServer, sid: str) -> dict[int, str | None]:
    """Who drew each of the session's defects (None: detected)."""
    engine = make_engine(live.settings.resolved_database_url())
    try:
        with make_sessionmaker(engine)() as db:
            rows = db.query(Defect.id, Defect.drawn_by).filter(Defect.session_id == sid).all()
            return {int(i): who for i, who in rows}
    finally:
        engine.dispose()


def _remove(live: LiveServer, ids: list[int]) -> None:
    engine = make_engine(live.settings.resolved_database_url())
    try:
        with make_sessionmaker(engine)() as db:
            db.execute(delete(Defect).where(Defect.id.in_(ids)))
            db.commit()
    finally:
        engine.dispose()


def test_drawn_defects_are_marked_and_unresolved_ones_left_out(
    inspected: tuple[LiveServer, str],
) -> None:
    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    box = {"bbox_x": 60, "bbox_y": 40, "bbox_w": 120, "bbox_h": 10}
    r = httpx.post(f"{api}/defects", json={"defect_class": "crack", **box})
    assert r.status_code == 201, r.text
    ids = [r.json()["id"]]
    try:
        ids += _tiny_detections(live, sid)
        listed = httpx.get(f"{api}/defects.json").json()
        rows = list(
            csv.DictReader(io.StringIO(httpx.get(f"{api}/defects.csv").text.lstrip("\ufeff")))
        )
        drawn = _drawn_by(live, sid)  # (other tests on the shared session may draw too)
        for records in (listed, rows):
            by_id = {int(d["id"]): d for d in records}
            assert by_id[ids[0]]["drawn_by"] == "anonymous"
            assert all((by_id[i]["drawn_by"] or None) == drawn[i] for i in by_id)
            assert ids[1] not in by_id and ids[2] not in by_id
        notes = httpx.get(f"{api}/report.json").json()["notes"]
        assert any("below the camera's resolution" in n for n in notes)
    finally:
        _remove(live, ids)
