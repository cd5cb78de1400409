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
