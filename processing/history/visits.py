"""Defects of two visits of one structure matched by position in the structure's frame:
new, grown, unchanged, or no longer seen, with the change of a crack's length and width and
of a rust patch's area.

A detector does not cut a defect the same way twice: one visit's crack may be another's two
pieces, and rust edges give short crack-like pieces that come and go. So the matching is of
groups, not of single detections:

1. a piece within a rust patch of its visit (boxes widened by ``tolerance_m``) smaller than
   half the patch's narrower side (a crack-like rust edge, a spot) is part of the patch;
2. defects of one class whose widened boxes overlap pair across the two visits, one to one,
   the closest centres together (an optimal assignment);
3. a piece left without a pair joins the pair whose pieces on its side of the visits it
   touches (a crack seen whole once and in pieces the other time), else stands alone;
4. a group is new without a piece in BEFORE, gone without one in AFTER; else grown when its
   cracks are longer in all by more than ``crack_growth_mm`` or its rust area grew by more
   than ``area_growth`` of the earlier area, else unchanged. Crack pieces of one visit only
   that touch one another are one group; such a group shorter than ``crack_growth_mm`` is
   left out (a speck of the detector: no growth can be told on it).

``tolerance_m`` is how well the visits' frames agree (their registration).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

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
    """One defect across two visits (``before`` or ``after`` None where it is not seen):
    each side the merge of its pieces (:func:`merge`), whose ids are in ``parts_before`` and
    ``parts_after`` (the largest first)."""

    status: str  # new, grown, unchanged, gone
    before: VisitDefect | None
    after: VisitDefect | None
    parts_before: tuple[int, ...] = field(default=())
    parts_after: tuple[int, ...] = field(default=())

    def delta(self, field: str) -> float | None:
        """AFTER's value minus BEFORE's for ``field`` (length_mm, width_mm, area_mm2)."""
        if self.before is None or self.after is None:
            return None
        a, b = getattr(self.after, field), getattr(self.before, field)
        return None if a is None or b is None else round(a - b, 3)


def _near(a: Box, b: Box, tol: float) -> bool:
    return a[0] - tol <= b[2] and b[0] - tol <= a[2] and a[1] - tol <= b[3] and b[1] - tol <= a[3]


def _inside(a: Box, b: Box, tol: float) -> bool:
    return a[0] >= b[0] - tol and a[1] >= b[1] - tol and a[2] <= b[2] + tol and a[3] <= b[3] + tol


def _part_of(piece: VisitDefect, rust: VisitDefect, tol: float) -> bool:
    """Whether a piece is part of a rust patch: inside it and smaller than half its narrower
    side (a crack-like edge of the rust, a spot of its own; a crack that crosses into a
    patch, or is long beside it, is a crack)."""
    narrow_mm = min(rust.box[2] - rust.box[0], rust.box[3] - rust.box[1]) * 1000
    extent_mm = max(piece.box[2] - piece.box[0], piece.box[3] - piece.box[1]) * 1000
    if piece.defect_class == "crack":
        extent_mm = max(extent_mm, piece.length_mm or 0.0)
    return piece.id != rust.id and _inside(piece.box, rust.box, tol) and extent_mm < narrow_mm / 2


def _size(d: VisitDefect) -> float:
    return d.area_mm2 or d.length_mm or 0.0


def _sum(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(sum(known), 3) if known else None


def merge(parts: Sequence[VisitDefect]) -> VisitDefect:
    """One defect of several pieces of one class: the largest piece's id, the boxes'
    union, lengths and areas summed, the widest width."""
    main = max(parts, key=_size)
    widths = [p.width_mm for p in parts if p.width_mm is not None]
    return VisitDefect(
        main.id,
        main.defect_class,
        (
            min(p.box[0] for p in parts),
            min(p.box[1] for p in parts),
            max(p.box[2] for p in parts),
            max(p.box[3] for p in parts),
        ),
        _sum([p.length_mm for p in parts]),
        max(widths) if widths else None,
        _sum([p.area_mm2 for p in parts]),
    )


def _fold_into_rust(defects: Sequence[VisitDefect], tol: float) -> list[list[VisitDefect]]:
    """The visit's defects as pieces: each rust patch with the smaller pieces inside it
    (:func:`_part_of` the largest patch holding them), each other defect alone."""
    rust = sorted((d for d in defects if d.defect_class == "corrosion"), key=_size, reverse=True)
    holder = {d.id: next((r.id for r in rust if _part_of(d, r, tol)), None) for d in defects}
    pieces: dict[int, list[VisitDefect]] = {}
    for d in sorted(defects, key=lambda d: holder[d.id] is not None):
        h = holder[d.id]
        while h is not None and holder[h] is not None:  # a piece of a piece of a patch
            h = holder[h]
        pieces.setdefault(d.id if h is None else h, []).append(d)
    return [pieces[d.id] for d in defects if d.id in pieces]


def _unresolved(d: VisitDefect, p: VisitParams) -> bool:
    """A crack seen on one visit only that is shorter than the growth the matching can tell
    (``crack_growth_mm``): a detector's speck, not a defect to report as new or gone."""
    return d.defect_class == "crack" and (d.length_mm or 0.0) < p.crack_growth_mm


def _grown(b: VisitDefect, a: VisitDefect, p: VisitParams) -> bool:
    if a.defect_class == "crack":
        return (a.length_mm or 0.0) - (b.length_mm or 0.0) > p.crack_growth_mm
    return (a.area_mm2 or 0.0) > (1 + p.area_growth) * (b.area_mm2 or 0.0)


def _pairs(heads_b: list[VisitDefect], heads_a: list[VisitDefect], tol: float) -> dict[int, int]:
    """One-to-one pairs (AFTER index -> BEFORE index) of one class whose widened boxes
    overlap, the closest centres together (an optimal assignment)."""
    big = 1e9
    cost = np.full((len(heads_b), len(heads_a)), big)
    for i, b in enumerate(heads_b):
        for j, a in enumerate(heads_a):
            if a.defect_class == b.defect_class and _near(b.box, a.box, tol):
                cost[i, j] = float(np.linalg.norm(_centre(a.box) - _centre(b.box)))
    if not cost.size:
        return {}
    rows, cols = linear_sum_assignment(cost)
    return {int(c): int(r) for r, c in zip(rows, cols, strict=True) if cost[r, c] < big}


def _centre(b: Box) -> np.ndarray:
    return np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])


def _union(parts: Sequence[VisitDefect]) -> Box:
    return merge(parts).box


def _attach(
    groups: list[tuple[list[int], list[int]]],
    leftovers: list[int],
    heads: list[VisitDefect],
    side: int,
    tol: float,
) -> None:
    """Pieces without a pair join the group whose pieces on their side they touch (boxes
    widened by ``tol``, the closest group), repeatedly, so a crack's several pieces join;
    the rest become groups of their own."""
    waiting = list(leftovers)
    joined = True
    while waiting and joined:
        joined = False
        for k in list(waiting):
            piece = heads[k]
            near = [
                g
                for g in groups
                if g[side]
                and heads[g[side][0]].defect_class == piece.defect_class
                and _near(_union([heads[m] for m in g[side]]), piece.box, tol)
            ]
            if near:
                best = min(
                    near,
                    key=lambda g: float(
                        np.linalg.norm(
                            _centre(_union([heads[m] for m in g[side]])) - _centre(piece.box)
                        )
                    ),
                )
                best[side].append(k)
                waiting.remove(k)
                joined = True
    # the rest: pieces of one crack that touch one another are one defect
    while waiting:
        cluster = [waiting.pop(0)]
        grew = True
        while grew:
            grew = False
            for k in list(waiting):
                piece = heads[k]
                if piece.defect_class == "crack" and any(
                    heads[m].defect_class == "crack" and _near(heads[m].box, piece.box, tol)
                    for m in cluster
                ):
                    cluster.append(k)
                    waiting.remove(k)
                    grew = True
        groups.append(([], cluster) if side == 1 else (cluster, []))


def match_visits(
    before: Sequence[VisitDefect], after: Sequence[VisitDefect], params: VisitParams = VisitParams()
) -> list[DefectChange]:
    """Each defect of either visit in one change: the pairs and AFTER's new ones in AFTER's
    order, then those seen in BEFORE only."""
    tol = params.tolerance_m
    fb, fa = _fold_into_rust(before, tol), _fold_into_rust(after, tol)
    hb, ha = [g[0] for g in fb], [g[0] for g in fa]
    pairs = _pairs(hb, ha, tol)
    groups: list[tuple[list[int], list[int]]] = [([pairs[j]], [j]) for j in sorted(pairs)]
    paired_b = set(pairs.values())
    _attach(groups, [j for j in range(len(ha)) if j not in pairs], ha, 1, tol)
    _attach(groups, [i for i in range(len(hb)) if i not in paired_b], hb, 0, tol)
    groups.sort(key=lambda g: (not g[1], min(g[1] or g[0])))
    out = []
    for ib, ia in groups:
        a = merge([ha[j] for j in ia]) if ia else None
        b = merge([hb[i] for i in ib]) if ib else None
        seen = a or b
        assert seen is not None
        if (a is None or b is None) and _unresolved(seen, params):
            continue  # shorter than any growth the visits can tell: no change to report
        if a is None:
            status = "gone"
        elif b is None:
            status = "new"
        else:
            status = "grown" if _grown(b, a, params) else "unchanged"
        out.append(DefectChange(status, b, a, _ids(fb, ib), _ids(fa, ia)))
    return out


def _ids(folded: list[list[VisitDefect]], ks: list[int]) -> tuple[int, ...]:
    """The ids of a group's pieces on one side, the largest first."""
    pieces = [d for k in ks for d in folded[k]]
    return tuple(d.id for d in sorted(pieces, key=_size, reverse=True))
