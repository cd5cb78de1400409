"""The PDF report's element condition table (AASHTO Manual for Bridge Element Inspection):
each element of the session's structure with its quantity in CS1-CS4, and under it the
quantities of each defect code found on it, as bridge management systems list them."""

from __future__ import annotations

from typing import Any

from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.platypus import Spacer

from server.reports.pdf_style import BODY_W, fmt_num, grid_table, para


def condition_table(report: dict[str, Any], st: dict[str, ParagraphStyle]) -> list[Any]:
    """The section, or nothing when the session inspects no structure on record."""
    ec = report.get("element_condition")
    if not ec:
        return []
    story: list[Any] = [
        para(f"Element condition — {ec['structure']}", st["h1"]),
        para(
            "Quantities per condition state by the AASHTO Manual for Bridge Element Inspection: "
            "a defect counts on the element holding it, cracks (1010) along the element's "
            "length or area, corrosion (1000) over its extent; the worst state holds where "
            "defects overlap. Defects rejected in review are left out.",
            st["body"],
        ),
        Spacer(1, 2 * mm),
    ]
    rows: list[list[Any]] = [["Element", "Defect", "Unit", "Total", "CS1", "CS2", "CS3", "CS4"]]
    for e in ec["elements"]:
        cs = e["cs"]
        rows.append(
            [f"{e['number']} {e['name']}", "", e["unit"], fmt_num(e["quantity"], "{:.2f}")]
            + [fmt_num(cs[f"cs{k}"], "{:.2f}") for k in range(1, 5)]
        )
        for d in e["by_defect"]:
            affected = [d[f"cs{k}"] for k in (2, 3, 4)]
            rows.append(
                ["", f"{d['code']} {d['name']}", e["unit"], fmt_num(sum(affected), "{:.2f}"), "–"]
                + [fmt_num(v, "{:.2f}") for v in affected]
            )
    widths = [52 * mm, 40 * mm, 12 * mm] + [(BODY_W - 104 * mm) / 5] * 5
    story.append(grid_table(rows, widths))
    if ec["unplaced_defects"]:
        story += [
            Spacer(1, 2 * mm),
            para(
                f"{len(ec['unplaced_defects'])} defects lie on no element defined for the "
                "structure.",
                st["note"],
            ),
        ]
    return story


_STATUS = {"new": "new", "grown": "grown", "unchanged": "unchanged", "gone": "no longer seen"}


def changes_section(report: dict[str, Any], st: dict[str, ParagraphStyle]) -> list[Any]:
    """ "Changes since <date>": how the session was placed on the previous visit, each
    defect's change, and the elements whose condition worsened; nothing without a previous
    visit on record."""
    ch = report.get("changes_since")
    if not ch:
        return []
    reg = ch.get("registration")
    placed = (
        f"The mosaic was registered to the previous visit's: residual {reg['residual_mm']:.1f} mm "
        f"over {reg['overlap'] * 100:.0f} % of the surface."
        if reg
        else "The mosaics could not be registered: the session is placed by its marked datum."
    )
    counts = {k: sum(c["status"] == k for c in ch["changes"]) for k in _STATUS}
    story: list[Any] = [
        para(f"Changes since {ch['previous_date']}", st["h1"]),
        para(
            f"{placed} {counts['new']} new, {counts['grown']} grown, {counts['unchanged']} "
            f"unchanged, {counts['gone']} no longer seen.",
            st["body"],
        ),
        Spacer(1, 2 * mm),
    ]
    rows: list[list[Any]] = [["Defect", "Class", "Change", "Before", "After", "Length +", "Area +"]]
    for c in ch["changes"]:
        if c["status"] == "unchanged":
            continue
        b, a = c["before"] or {}, c["after"] or {}
        rows.append(
            [
                f"#{a.get('number') or b.get('number') or '–'}",
                c["class"],
                _STATUS[c["status"]],
                fmt_num(b.get("length_mm"), "{:.0f}", " mm") if b else "–",
                fmt_num(a.get("length_mm"), "{:.0f}", " mm") if a else "–",
                fmt_num(c["length_change_mm"], "{:+.1f}", " mm"),
                fmt_num(c["area_change_mm2"], "{:+.0f}", " mm²"),
            ]
        )
    if len(rows) > 1:
        story.append(grid_table(rows, [20 * mm, 24 * mm, 28 * mm] + [(BODY_W - 72 * mm) / 4] * 4))
    for e in ch["worsened_elements"]:
        story.append(
            para(
                f"Element {e['number']} worsened: CS3+CS4 "
                f"{e['before']['cs3'] + e['before']['cs4']:.2f} to "
                f"{e['after']['cs3'] + e['after']['cs4']:.2f}.",
                st["note"],
            )
        )
    return story
