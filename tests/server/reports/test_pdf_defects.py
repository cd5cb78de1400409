"""The PDF's defect table, built from a report's records without a station."""

from __future__ import annotations

from typing import Any

from reportlab.platypus import Table

from server.reports.pdf_defects import defect_table
from server.reports.pdf_style import make_styles


def record(**fields: Any) -> dict[str, Any]:
    base = dict.fromkeys(("length_mm", "max_width_mm", "area_mm2", "condition_state"))
    return {
        **base,
        "number": 8,
        "defect_class": "crack",
        "review_status": "unreviewed",
        "comment": "",
        **fields,
    }


def test_the_position_column_names_the_box_corner_the_dashboard_shows() -> None:
    d = record(world_x_m=0.544, world_y_m=0.465, world_w_m=0.076, world_h_m=0.084)
    story = defect_table({"defects": [d], "missing": {}}, make_styles(), lambda _: None)
    table = next(f for f in story if isinstance(f, Table))
    header, row = table._cellvalues[0], table._cellvalues[1]
    column = next(i for i, h in enumerate(header) if "x, y (m)" in str(h))
    assert header[column] == "Box corner\nx, y (m)"
    assert row[column] == "0.544,\n0.465"
    intro = " ".join(getattr(f, "text", "") for f in story)
    assert "Position: the corner of the defect's box nearest the structure's origin" in intro


def test_a_defect_drawn_by_a_reviewer_is_marked_in_its_row() -> None:
    drawn = record(world_x_m=0.1, world_y_m=0.2, drawn_by="anna", review_status="confirmed")
    found = record(world_x_m=0.3, world_y_m=0.2, number=9)
    story = defect_table({"defects": [drawn, found], "missing": {}}, make_styles(), lambda _: None)
    table = next(f for f in story if isinstance(f, Table))
    header, *rows = table._cellvalues
    column = header.index("Class")
    classes = [getattr(r[column], "text", r[column]) for r in rows]
    assert "drawn by anna" in classes[0] and "drawn by" not in classes[1]
