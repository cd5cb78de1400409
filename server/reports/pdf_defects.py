"""The PDF report's defect table: a row per defect not rejected in review, with its
number (linked to the dashboard), thumbnail, sizes, position, review and condition state,
and the comments too long for a cell in full after it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.platypus import Paragraph, Spacer

from server.reports.fields import POSITION_MEANING
from server.reports.pdf_style import BODY_W, fmt_num, grid_table, para, picture

Thumbnail = Callable[[dict[str, Any]], np.ndarray | None]


def defect_table(
    report: dict[str, Any], st: dict[str, ParagraphStyle], thumbnail: Thumbnail
) -> list[Any]:
    """The report's defects section: the table (images from ``thumbnail``), or why there
    is none."""
    listed = [d for d in report["defects"] if d["review_status"] != "rejected"]
    story: list[Any] = [para("Defects", st["h1"])]
    if not report["defects"]:
        done = "detect" not in report["missing"]
        return story + [
            para(
                "No defect was found."
                if done
                else "Defect detection has not run for this session.",
                st["body"],
            )
        ]
    rejected = len(report["defects"]) - len(listed)
    intro = (
        f"{len(listed)} defects, ordered along the structure; numbers match the markers on the mosaic. "
        f"Position: {POSITION_MEANING} (x, y in metres, world frame; world_x_m, world_y_m in defects.csv); "
        'sizes from the camera scale; "drawn by" marks a defect a reviewer drew by hand.'
    )
    if rejected:
        intro += f" {rejected} defects rejected in review are not listed (they are in defects.csv)."
    story.append(para(intro, st["body"]))
    story.append(Spacer(1, 2 * mm))
    rows: list[list[Any]] = [
        [
            "#",
            "Image",
            "Class",
            "Length\nmm",
            "Max w.\nmm",
            "Area\nmm²",
            "Box corner\nx, y (m)",
            "Review",
            "CS",
            "Comment",
        ]
    ]
    rows += [_defect_row(d, st, thumbnail) for d in listed]
    widths = [8 * mm, 26 * mm, 16 * mm, 13 * mm, 13 * mm, 13 * mm, 18 * mm, 30 * mm, 9 * mm]
    widths.append(BODY_W - sum(widths))
    story.append(grid_table(rows, widths, font_size=8))
    long = [d for d in listed if d["comment"] and _clip(d["comment"]) != d["comment"]]
    if long:  # in full as running text, which may break across pages (a table row cannot)
        story += [Spacer(1, 3 * mm), para("Comments in full", st["h2"])]
        story += [para(f"#{d['number']}: {d['comment']}", st["body"]) for d in long]
    return story


def _defect_row(
    d: dict[str, Any], st: dict[str, ParagraphStyle], thumbnail: Thumbnail
) -> list[Any]:
    """One defect's row of the table: number (a link to it), thumbnail, class, sizes,
    position, review, condition state, comment."""
    thumb = thumbnail(d)
    cell = picture(thumb, 24 * mm, 24 * mm) if thumb is not None else "—"
    pos = f"{d['world_x_m']:.3f},\n{d['world_y_m']:.3f}" if d["world_x_m"] is not None else "—"
    review = d["review_status"] + (f"\nby {d['reviewed_by']}" if d.get("reviewed_by") else "")
    return [
        _number_link(d, st),
        cell,
        para(
            d["defect_class"] + (f"\ndrawn by {d['drawn_by']}" if d.get("drawn_by") else ""),
            st["cell"],
        ),
        fmt_num(d["length_mm"]),
        fmt_num(d["max_width_mm"], "{:.2f}"),
        fmt_num(d["area_mm2"], "{:.0f}"),
        pos,
        para(review, st["cell"]),
        d["condition_state"] or "—",
        para(_clip(d["comment"]), st["cell"]),
    ]


def _number_link(d: dict[str, Any], st: dict[str, ParagraphStyle]) -> Any:
    """The defect's number, linked to the dashboard on that defect when the report knows
    the station's address."""
    url = d.get("dashboard_url", "")
    if not url.startswith(("http://", "https://")):
        return str(d["number"])
    return Paragraph(
        f'<a href="{escape(url)}" color="#1f3a5f"><u>{d["number"]}</u></a>', st["cell"]
    )


def _clip(text: str | None, chars: int = 200, lines: int = 6) -> str | None:
    """A comment short enough for a table cell; longer ones end in "…" and follow the
    table in full."""
    if not text:
        return text
    rows = text.splitlines()
    short = "\n".join(rows[:lines])[:chars]
    words = short.split()
    if any(len(w) > 30 for w in words):  # one long "word" would fill the cell letter by letter
        short = " ".join(w[:30] for w in words)
    return text if short == text else short.rstrip() + " … (in full below)"
