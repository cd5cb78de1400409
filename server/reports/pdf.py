"""The inspection report as PDF (ReportLab platypus): cover, summary, mosaic overview with
numbered defects, defect table with thumbnails, 3D map snapshot, processing parameters."""

from __future__ import annotations

import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.platypus import (
    KeepTogether,
    PageBreak,
    SimpleDocTemplate,
    Spacer,
)
from sqlalchemy import select
from sqlalchemy.orm import Session

from processing.coverage import CoverageParams
from processing.poses import parse_tum
from processing.snapshot import render_points
from server.errors import NotFound
from server.reports.content import build_report, read_json
from server.reports.fields import CONDITION_MEANING, CONDITION_STATES
from server.reports.pdf_condition import changes_section, condition_table
from server.reports.pdf_defects import Thumbnail, defect_table
from server.reports.pdf_sections import coverage_section, parameters_appendix
from server.reports.pdf_style import (
    BODY_W,
    MARGIN,
    MARKER_BGR,
    PAGE_H,
    PAGE_W,
    fmt_num,
    grid_table,
    make_styles,
    para,
    picture,
)
from server.storage.files import SessionFiles
from server.storage.models import Defect
from server.storage.ply import read_ply_points
from server.storage.thumbnails import defect_image


def overview_with_markers(
    overview: np.ndarray, defects: list[dict[str, Any]], scale: float
) -> np.ndarray:
    """The mosaic overview with each defect's box and number drawn (``scale``: overview px per mosaic px)."""
    out = overview.copy()
    line = max(1, round(max(out.shape[:2]) / 700))
    for d in defects:
        x, y = d["bbox_x"] * scale, d["bbox_y"] * scale
        w, h = max(d["bbox_w"] * scale, 3), max(d["bbox_h"] * scale, 3)
        colour = (150, 150, 150) if d["review_status"] == "rejected" else MARKER_BGR
        cv2.rectangle(out, (round(x), round(y)), (round(x + w), round(y + h)), colour, line)
        label, font = str(d["number"]), cv2.FONT_HERSHEY_SIMPLEX
        fs = 0.45 * line
        (tw, th), _ = cv2.getTextSize(label, font, fs, line)
        tx, ty = round(x + w + 2), max(th + 2, round(y))
        cv2.rectangle(out, (tx - 1, ty - th - 2), (tx + tw + 1, ty + 2), (255, 255, 255), -1)
        cv2.putText(out, label, (tx, ty), font, fs, colour, line, cv2.LINE_AA)
    return out


def _cover(report: dict[str, Any], st: dict[str, ParagraphStyle]) -> list[Any]:
    c = report["cover"]
    story: list[Any] = [
        Spacer(1, 18 * mm),
        para("Steel structure inspection report", st["title"]),
        para(c["structure"], st["subtitle"]),
        Spacer(1, 10 * mm),
    ]
    rows = [
        ["Structure", para(c["structure"], st["cover"])],
        ["Location", para(c["location"] or "not recorded", st["cover"])],
        ["Date", c["date"]],
        ["Started / ended (UTC)", f"{c['started_at']}  /  {c['ended_at'] or 'still live'}"],
        ["Operator", para(c["operator"] or "not recorded", st["cover"])],
        ["Robot", para(c["robot"] or "unknown", st["cover"])],
        ["Session", c["session_id"]],
        ["Report generated", f"{report['generated_at']} by {report['generator']}"],
    ]
    story.append(grid_table(rows, [48 * mm, BODY_W - 48 * mm], header=False, font_size=10))
    if c.get("notes"):
        story += [Spacer(1, 4 * mm), para(f"Notes: {c['notes']}", st["body"])]
    story.append(PageBreak())
    return story


def _summary(report: dict[str, Any], st: dict[str, ParagraphStyle]) -> list[Any]:
    s = report["summary"]
    rows = [
        ["Area covered", fmt_num(s["area_covered_m2"], "{:.2f}", " m²")],
        ["Distance travelled (odometry)", fmt_num(s["distance_travelled_m"], "{:.2f}", " m")],
        ["Duration", duration_text(s["duration_s"])],
        [
            "Camera frames / ToF clouds / telemetry",
            f"{s['frames']} / {s['clouds']} / {s['telemetry_samples']}",
        ],
        ["Defects found (listed)", f"{s['defects']} ({s['defects_rejected']} rejected by review)"],
        [
            "Cracks / corrosion areas (not rejected)",
            f"{s['defects_by_class']['crack']} / {s['defects_by_class']['corrosion']}",
        ],
        [
            "Longest / widest crack",
            f"{fmt_num(s['longest_crack_mm'], unit=' mm')} / {fmt_num(s['widest_crack_mm'], '{:.2f}', ' mm')}",
        ],
        ["Total crack length", fmt_num(s["total_crack_length_mm"], unit=" mm")],
        [
            "Corroded area",
            fmt_num(
                s["corroded_area_mm2"] / 100 if s["corroded_area_mm2"] is not None else None,
                "{:.1f}",
                " cm²",
            ),
        ],
        ["Review", ", ".join(f"{v} {k}" for k, v in s["defects_by_review"].items())],
    ]
    story: list[Any] = [
        para("Summary", st["h1"]),
        grid_table(rows, [75 * mm, BODY_W - 75 * mm], header=False, font_size=9.5),
    ]
    cs = s["defects_by_condition_state"]
    cs_rows = [["Condition state", "Meaning", "Defects"]] + [
        [k, CONDITION_MEANING[k], cs[k]] for k in CONDITION_STATES
    ]
    cs_rows.append(["—", "not rated yet", cs["not rated"]])
    cs_table = grid_table(cs_rows, [35 * mm, 50 * mm, 25 * mm])
    cs_table.hAlign = "LEFT"
    story += [para("Defects by condition state", st["h2"]), cs_table]
    story += coverage_section(report.get("coverage"), st)
    for note in report["notes"]:
        story += [Spacer(1, 2 * mm), para(note, st["note"])]
    return story


def duration_text(seconds: float | None) -> str:
    """A duration as an inspector says it: "12 min 05 s", "1 h 02 min"."""
    if seconds is None:
        return "—"
    total = round(seconds)
    h, rest = divmod(total, 3600)
    m, sec = divmod(rest, 60)
    return f"{h} h {m:02d} min" if h else f"{m} min {sec:02d} s" if m else f"{sec} s"


def _missing(report: dict[str, Any], what: str) -> str:
    """The report's note on why a result is missing (it starts with ``what``)."""
    return next((n for n in report["notes"] if n.startswith(what)), f"{what}: not available.")


def _footer(structure: str) -> Callable[[Any, Any], None]:
    def draw(canvas: Any, doc: Any) -> None:
        canvas.saveState()
        canvas.setFont("Helvetica", 7.5)
        canvas.setFillColor(colors.HexColor("#666666"))
        canvas.drawString(MARGIN, 9 * mm, f"steelscan inspection report — {structure}"[:110])
        canvas.drawRightString(PAGE_W - MARGIN, 9 * mm, f"page {doc.page}")
        canvas.restoreState()

    return draw


def _mosaic_page(report: dict[str, Any], st: Any, marked: np.ndarray | None) -> list[Any]:
    """The mosaic with the listed defects marked, or why there is none."""
    story: list[Any] = [para("Mosaic of the inspected surface", st["h1"])]
    if marked is None:
        return story + [para(_missing(report, "No mosaic"), st["body"])]
    return story + [
        para(
            "The downward camera's frames stitched in world coordinates; red boxes and numbers "
            "mark the listed defects (grey: rejected in review).",
            st["body"],
        ),
        Spacer(1, 3 * mm),
        picture(marked, BODY_W, PAGE_H - 2 * MARGIN - 40 * mm),
    ]


def _map_page(report: dict[str, Any], st: Any, snapshot: np.ndarray | None) -> list[Any]:
    """The 3D map's picture, or why there is none."""
    story: list[Any] = [para("3D map of the structure", st["h1"])]
    if snapshot is None:
        return story + [para(_missing(report, "No 3D map"), st["body"])]
    pts = report["summary"].get("map_points")
    return story + [
        para(
            f"Registered ToF point clouds ({pts or '?'} points after voxel filtering), coloured "
            "by height; the black line is the robot's trajectory.",
            st["body"],
        ),
        Spacer(1, 3 * mm),
        KeepTogether(picture(snapshot, BODY_W, 150 * mm)),
    ]


def write_report_pdf(
    report: dict[str, Any],
    path: Path,
    *,
    overview: np.ndarray | None = None,
    overview_scale: float = 1.0,
    map_snapshot: np.ndarray | None = None,
    thumbnail: Thumbnail = lambda d: None,
) -> Path:
    """Write the PDF of ``report`` (from :func:`server.reports.content.build_report`) to ``path``
    atomically; images are given as BGR arrays, thumbnails fetched per defect record."""
    st = make_styles()
    marked = (
        overview_with_markers(overview, report["defects"], overview_scale)
        if overview is not None
        else None
    )
    story = _cover(report, st)
    story += _summary(report, st)
    story.append(PageBreak())
    story += _mosaic_page(report, st, marked)
    story.append(PageBreak())
    story += defect_table(report, st, thumbnail)
    story += changes_section(report, st)
    story += condition_table(report, st)
    story.append(PageBreak())
    story += _map_page(report, st, map_snapshot)
    story += [PageBreak()] + parameters_appendix(report, st)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    footer = _footer(report["cover"]["structure"])
    doc = SimpleDocTemplate(
        str(tmp),
        pagesize=A4,
        leftMargin=MARGIN,
        rightMargin=MARGIN,
        topMargin=MARGIN,
        bottomMargin=MARGIN + 4 * mm,
        title=f"Inspection report — {report['cover']['structure']}",
        author=report["cover"]["operator"] or "steelscan",
        subject=f"session {report['cover']['session_id']}",
        creator=report["generator"],
    )
    try:
        doc.build(story, onFirstPage=footer, onLaterPages=footer)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_pdf(
    db: Session,
    files: SessionFiles,
    session_id: str,
    path: Path,
    *,
    base_url: str = "",
    coverage: CoverageParams | None = None,
) -> Path:
    """Build the report of a session and write it as PDF to ``path`` (atomically)."""
    report = build_report(
        db, files, session_id, base_url=base_url, coverage=coverage or CoverageParams()
    )
    results = files.results_dir(session_id)
    overview, scale = None, 1.0
    if "stitch" not in report["missing"]:
        overview = cv2.imread(str(results / "mosaic_overview.png"), cv2.IMREAD_COLOR)
        world = read_json(results / "mosaic.json") or {}
        scale = float(world.get("overview_scale", 1.0))
    snapshot = map_snapshot(results) if "map" not in report["missing"] else None
    by_id = {d.id: d for d in db.scalars(select(Defect).where(Defect.session_id == session_id))}

    def thumbnail(rec: dict[str, Any]) -> Any:
        try:
            return defect_image(db, files, by_id[rec["id"]], size=192)
        except (NotFound, KeyError, ValueError, OSError):
            return None

    return write_report_pdf(
        report,
        path,
        overview=overview,
        overview_scale=scale,
        map_snapshot=snapshot,
        thumbnail=thumbnail,
    )


def map_snapshot(results: Path) -> Any:
    """Picture of ``map.ply`` with the trajectory of ``trajectory.tum``, or None without a map."""
    try:
        points = read_ply_points(results / "map.ply")
    except (OSError, ValueError):
        return None
    path = None
    try:
        _, poses = parse_tum((results / "trajectory.tum").read_text())
        path = poses[:, :3, 3]
    except (OSError, ValueError):
        pass
    return render_points(points, path=path)
