"""The PDF's tables of facts, built from a report's data without a station."""

from __future__ import annotations

from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.platypus import Paragraph, Table

from server.reports.pdf_sections import coverage_section
from server.reports.pdf_style import make_styles


def test_every_coverage_cell_fits_its_column() -> None:
    cov = {
        "required_mm_per_px": 0.3,
        "area_imaged_m2": 1.234,
        "area_surface_m2": 2.5,
        "fraction_imaged": 0.49,
        "frames_not_counted": 3,
        "frames_not_counted_by_reason": {"blurred": 2, "too far": 1},
        "holes": [],
    }
    story = coverage_section(cov, make_styles())
    table = next(f for f in story if isinstance(f, Table))
    padding = 12  # ReportLab's default left and right cell padding, together
    for row in table._cellvalues:
        for cell, width in zip(row, table._colWidths, strict=True):
            if isinstance(cell, Paragraph):
                continue  # a paragraph wraps within its cell
            text_w = stringWidth(str(cell), "Helvetica-Bold", 9.5)
            assert text_w <= width - padding, f"{cell!r} runs over its cell"
