"""Sections of the PDF report that are tables of facts: coverage with its holes, and the
appendix of processing parameters and calibration."""

from __future__ import annotations

import json
from typing import Any

from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.platypus import Spacer

from server.reports.pdf_style import BODY_W, grid_table, para


def coverage_section(cov: dict[str, Any] | None, st: dict[str, ParagraphStyle]) -> list[Any]:
    """Coverage: the surface imaged well enough to count, and the holes to go back to."""
    if not cov:
        return []
    story: list[Any] = [para("Coverage", st["h2"])]
    if not cov["area_surface_m2"]:
        return story + [para("No frame with a pose and a camera scale: no coverage.", st["body"])]
    why = ", ".join(f"{n} {r}" for r, n in cov["frames_not_counted_by_reason"].items())
    facts = [
        (
            f"Surface imaged at ≤ {cov['required_mm_per_px']:g} mm/px, sharp and exposed",
            f"{cov['area_imaged_m2']:.3f} of {cov['area_surface_m2']:.3f} m² in view "
            f"({cov['fraction_imaged'] * 100:.1f} %)",
        ),
        ("Frames not counted", f"{cov['frames_not_counted']}" + (f" ({why})" if why else "")),
        ("Holes", str(len(cov["holes"]))),
    ]
    # paragraphs, which wrap within their cell (a plain string runs over the next one)
    rows = [[para(label, st["label"]), para(value, st["body"])] for label, value in facts]
    story.append(grid_table(rows, [75 * mm, BODY_W - 75 * mm], header=False, font_size=9.5))
    if cov["holes"]:
        holes = [["Hole", "Centre x, y (m)", "Extent w × h (m)", "Area (cm²)"]] + [
            [
                str(i + 1),
                f"{h['x_m']:.3f}, {h['y_m']:.3f}",
                f"{h['bbox_m'][2]:.3f} × {h['bbox_m'][3]:.3f}",
                f"{h['area_m2'] * 1e4:.1f}",
            ]
            for i, h in enumerate(cov["holes"][:15])
        ]
        table = grid_table(holes, [15 * mm, 40 * mm, 40 * mm, 25 * mm], font_size=8.5)
        table.hAlign = "LEFT"
        story += [Spacer(1, 2 * mm), table]
        if len(cov["holes"]) > 15:
            story.append(
                para(f"… and {len(cov['holes']) - 15} smaller holes (report.json).", st["note"])
            )
    return story


def parameters_appendix(report: dict[str, Any], st: dict[str, ParagraphStyle]) -> list[Any]:
    story: list[Any] = [
        para("Appendix — processing parameters and calibration", st["h1"]),
        para(
            "The parameters each processing stage ran with and the sensors' calibration, for "
            "repeating or auditing the results.",
            st["body"],
        ),
    ]
    if not report["parameters"]:
        return story + [para("No processing job has finished for this session.", st["body"])]
    for kind, params in report["parameters"].items():
        flat = _flatten(params)
        rows = [["Parameter", "Value"]] + [[k, para(v, st["small"])] for k, v in flat.items()]
        if len(rows) == 1:
            rows.append(["(defaults)", ""])
        story += [
            para(
                {
                    "stitch": "Mosaic (stitching)",
                    "map": "3D map (ICP)",
                    "detect": "Defect detection",
                }.get(kind, kind),
                st["h2"],
            ),
            grid_table(rows, [70 * mm, BODY_W - 70 * mm], font_size=7.5),
        ]
    cal = report.get("calibration") or {}
    if cal:
        rows = [["Calibration", "Value"]] + [
            [k, para(v, st["small"])] for k, v in _flatten(cal).items()
        ]
        story += [
            para("Sensor calibration", st["h2"]),
            grid_table(rows, [70 * mm, BODY_W - 70 * mm], font_size=7.5),
        ]
    return story


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out |= _flatten(v, key + ".")
        else:
            out[key] = json.dumps(v) if isinstance(v, (list, tuple)) else str(v)
    return out
