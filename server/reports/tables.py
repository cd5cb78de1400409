"""Defects as a CSV table that spreadsheets open safely."""

from __future__ import annotations

import csv
import io
import unicodedata
from collections.abc import Iterable, Iterator
from typing import Any

from server.reports.fields import DEFECT_FIELDS

FORMULA_START = frozenset("=+-@|%")  # what spreadsheets start a formula or DDE call with
INVISIBLE = frozenset({"Cf", "Cc", "Zs"})  # format and control characters, odd spaces


def _cell(value: Any) -> Any:
    """A CSV cell; text that a spreadsheet would run as a formula is quoted with a leading
    apostrophe (CSV injection), numbers and empty values pass as they are."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str) and _formula_like(value):
        return "'" + value
    return value


def _formula_like(text: str) -> bool:
    """Whether a spreadsheet might read the text as a formula: its first visible character,
    once full-width forms are folded (＝ is =), starts one, or it starts with a control
    or invisible format character (a zero-width space, a byte-order mark) that some
    spreadsheets skip."""
    if text[:1] in ("\t", "\r", "\n"):
        return True
    visible = text.lstrip()
    while visible and unicodedata.category(visible[0]) in INVISIBLE:  # U+200B, U+FEFF, ...
        visible = visible[1:].lstrip()
    if len(visible) != len(text.lstrip()):
        return True  # a cell that hides its first character is quoted whatever follows
    head = unicodedata.normalize("NFKC", visible)[:1]
    return head in FORMULA_START


def defects_csv(records: Iterable[dict[str, Any]]) -> Iterator[str]:
    """``defects.csv`` line by line: a UTF-8 byte-order mark (so spreadsheets read accents),
    a header, one row per defect record of :func:`server.reports.content.build_report`."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\r\n")
    writer.writerow(DEFECT_FIELDS)
    yield "\ufeff" + buf.getvalue()
    for rec in records:
        buf.seek(0)
        buf.truncate()
        writer.writerow([_cell(rec.get(k)) for k in DEFECT_FIELDS])
        yield buf.getvalue()
