"""Defects of two visits of one structure matched by position in the structure's frame:
new, grown, unchanged, or no longer seen, with the change of a crack's length and width and
of a rust patch's area.

Two defects of one class are the same when their boxes, each widened by ``tolerance_m``
(how well the visits' frames agree), overlap; among several candidates the closest centres
pair up (an optimal assignment). A crack has grown when it is longer by more than
``crack_growth_mm``, a rust patch when its area grew by more than ``area_growth``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

Box = tuple[float, float, float, float]  # x0, y0, x1, y1 (m)


@dataclass(frozen=True)
class VisitDefect:
    """A defect of one visit as the matching sees it."""

    id: int
    defect_class: str
    box: Box
    length_mm: float | None = None
    width_mm: float | None = None
    area_mm2: float | None = None


@dataclass(frozen=True)
class VisitParams:
    """When two visits' defects are one, and when it grew."""

    tolerance_m: float = 0.01
    crack_growth_mm: float = 3.0
    area_growth: float = 0.2  # fraction of the earlier area


@dataclass(frozen=True)
class DefectChange:
    """One defect across two visits (``before`` or ``after`` None where it is not seen)."""

    status: str  # new, grown, unchanged, gone
    before: VisitDefect | None
    after: VisitDefect | None

    def delta(self, field: str) -> float | None:
        """AFTER's value minus BEFORE's for ``field`` (length_mm, width_mm, area_mm2)."""
        if self.before is None or self.after is None:
            return None
        a, b = getattr(self.after, field), getattr(self.before, field)
        return None if a is None or b is None else round(a - b, 3)


def _centre(b: Box) -> np.ndarray:
    return np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])


def _near(a: Box, b: Box, tol: float) -> bool:
    return a[0] - tol <= b[2] and b[0] - tol <= a[2] and a[1] - tol <= b[3] and b[1] - tol <= a[3]


def _grown(b: VisitDefect, a: VisitDefect, p: VisitParams) -> bool:
    if a.defect_class == "crack":
        return (a.length_mm or 0.0) - (b.length_mm or 0.0) > p.crack_growth_mm
    return (a.area_mm2 or 0.0) > (1 + p.area_growth) * (b.area_mm2 or 0.0)


def match_visits(
    before: Sequence[VisitDefect], after: Sequence[VisitDefect], params: VisitParams = VisitParams()
) -> list[DefectChange]:
    """Each defect of either visit once, in AFTER's order then BEFORE's unmatched ones."""
    big = 1e9
    cost = np.full((len(before), len(after)), big)
    for i, b in enumerate(before):
        for j, a in enumerate(after):
            if a.defect_class == b.defect_class and _near(b.box, a.box, params.tolerance_m):
                cost[i, j] = float(np.linalg.norm(_centre(a.box) - _centre(b.box)))
    pairs: dict[int, int] = {}
    if cost.size:
        rows, cols = linear_sum_assignment(cost)
        pairs = {int(c): int(r) for r, c in zip(rows, cols, strict=True) if cost[r, c] < big}
    out = []
    for j, a in enumerate(after):
        if j in pairs:
            b = before[pairs[j]]
            out.append(DefectChange("grown" if _grown(b, a, params) else "unchanged", b, a))
        else:
            out.append(DefectChange("new", None, a))
    matched = set(pairs.values())
    out += [DefectChange("gone", b, None) for i, b in enumerate(before) if i not in matched]
    return out
