"""Scores of ``steelscan bench history`` against the simulator's truth: where the station
placed a visit, how it matched each defect to the previous visit's, what growth it measured,
and its element condition table."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from processing.history.condition import CodedDefect, Element, element_of, state_quantities
from processing.poses import se2_matrix
from robot_link.sim.aging import Growth
from robot_link.sim.structure import SteelStructure, TrueDefect

Box = tuple[float, float, float, float]
TOUCH_M = 0.005  # a detection belongs to a true defect whose box it meets within this


@dataclass(frozen=True)
class VisitTruth:
    """One visit: the structure as it was, its growth since the previous visit, and where
    the robot was set down relative to the datum (x, y in metres, yaw in radians)."""

    structure: SteelStructure
    growth: list[Growth]
    start_offset: tuple[float, float, float]


def _box(t: TrueDefect) -> Box:
    x, y, w, h = t.bbox_m
    return (x, y, x + w, y + h)


def truth_of(box: Sequence[float] | None, truth: Sequence[TrueDefect]) -> int | None:
    """The true defect a detection's structure-frame box belongs to: of those it meets,
    the one with the nearest centre; None for a detection of nothing."""
    if box is None:
        return None
    best, best_d = None, np.inf
    c = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])
    for t in truth:
        b = _box(t)
        if (
            box[0] - TOUCH_M <= b[2]
            and b[0] - TOUCH_M <= box[2]
            and box[1] - TOUCH_M <= b[3]
            and b[1] - TOUCH_M <= box[3]
        ):
            d = float(np.linalg.norm(c - [(b[0] + b[2]) / 2, (b[1] + b[3]) / 2]))
            if d < best_d:
                best, best_d = t.id, d
    return best


def mosaic_anchor(world: dict[str, Any], true_poses: Sequence[Sequence[float]]) -> np.ndarray:
    """The rigid transform (3x3) that best takes a visit's stitched frame centres (its world
    frame, from ``mosaic.json``) to their true places on the structure: where the visit's
    mosaic truly lies."""
    est = np.array(
        [
            np.asarray(world["origin_m"]) + np.array([f["x"], f["y"]]) / world["px_per_m"]
            for f in world["frames"]
        ]
    )
    truth = np.asarray(true_poses, float)[: len(est), :2]
    ms, mt = est.mean(0), truth.mean(0)
    U, _, Vt = np.linalg.svd((truth - mt).T @ (est - ms))
    R = U @ np.diag([1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(3)
    T[:2, :2], T[:2, 2] = R, mt - R @ ms
    return T


def _datum(d: dict[str, Any] | None) -> np.ndarray:
    d = d or {}
    return se2_matrix(float(d.get("x", 0.0)), float(d.get("y", 0.0)), float(d.get("yaw", 0.0)))


def score_placement(
    registration: dict[str, Any] | None,
    anchors: tuple[np.ndarray, np.ndarray],
    previous_datum: dict[str, Any] | None,
    true_poses: Sequence[Sequence[float]],
) -> dict[str, Any]:
    """How well a visit is placed, over the surface it imaged (its true frame centres q):

    - ``registration_mm``: the largest distance between where this visit's placement and
      the previous visit's put the same point of steel (each through its own mosaic:
      ``anchors`` are both mosaics' :func:`mosaic_anchor`);
    - ``absolute_mm``: the largest distance from the point's true place (the previous
      visits' own stitching and placement errors included);
    - ``marked_mm``: the same for the datum as marked (the identity), the baseline."""
    before, after = anchors
    q = np.column_stack([np.asarray(true_poses, float)[:, :2], np.ones(len(true_poses))])
    seen_before = q @ (_datum(previous_datum) @ np.linalg.inv(before)).T
    marked = q @ np.linalg.inv(after).T

    def worst(a: np.ndarray, b: np.ndarray) -> float:
        return round(float(np.max(np.linalg.norm((a - b)[:, :2], axis=1)) * 1000), 3)

    out: dict[str, Any] = {"marked_mm": worst(marked, seen_before), "registration_mm": None}
    if registration is not None:
        placed = q @ (_datum(registration["datum"]) @ np.linalg.inv(after)).T
        out["registration_mm"] = worst(placed, seen_before)
        out["absolute_mm"] = worst(placed, q)
        out["residual_mm"] = registration["residual_mm"]
    return out


def imaged(box: Box, poses: Sequence[Sequence[float]], footprint_m: tuple[float, float]) -> bool:
    """Whether a box's corners all lie in some camera frame of a visit (true camera poses
    x, y, yaw; footprint along and across the heading)."""
    p = np.asarray(poses, float)
    half = np.array(footprint_m) / 2
    for x, y in ((box[0], box[1]), (box[2], box[1]), (box[2], box[3]), (box[0], box[3])):
        d = np.array([x, y]) - p[:, :2]
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)
        if not np.any(np.all(np.abs(local) <= half, axis=1)):
            return False
    return True


def score_changes(
    changes: list[dict[str, Any]],
    before: VisitTruth,
    after: VisitTruth,
    seen: tuple[Sequence[Sequence[float]], Sequence[Sequence[float]]] | None = None,
    footprint_m: tuple[float, float] = (0.18, 0.135),
) -> dict[str, Any]:
    """Matching and growth against the truth: a true defect detected in both visits is
    matchable, and matched when a change pairs a detection of it in each visit; a pair of
    detections of two different true defects is a false match; a new or gone change where
    nothing truly appeared is a false change. Growth is scored once per true defect (its
    largest matched change), for defects each visit imaged whole (``seen``: both visits' true
    camera poses; a crack that grew beyond the surface a visit imaged is left out and
    counted in ``growth_not_imaged``)."""
    tb, ta = before.structure.defects, after.structure.defects
    growth = {g.defect_id: g for g in after.growth}
    seen_b: set[int] = set()
    seen_a: set[int] = set()
    matched: dict[int, dict[str, Any]] = {}
    out: dict[str, Any] = {"false_matches": 0, "false_changes": 0, "new_found": 0}
    for c in changes:
        ib = truth_of((c["before"] or {}).get("box_m"), tb)
        ia = truth_of((c["after"] or {}).get("box_m"), ta)
        seen_b |= {ib} - {None}  # type: ignore[arg-type]
        seen_a |= {ia} - {None}  # type: ignore[arg-type]
        if c["before"] and c["after"]:
            if ib is not None and ib == ia:
                if ia not in matched or _size(c) > _size(matched[ia]):
                    matched[ia] = c
            elif ib is not None or ia is not None:
                out["false_matches"] += 1
        elif c["status"] == "new" and ia is not None and ia in growth and growth[ia].new:
            out["new_found"] += 1
        elif c["status"] in ("new", "gone"):
            out["false_changes"] += 1
    both = seen_b & seen_a
    whole = {
        t.id
        for t in ta
        if seen is None
        or (
            imaged(_box(t), seen[1], footprint_m)
            and all(imaged(_box(o), seen[0], footprint_m) for o in tb if o.id == t.id)
        )
    }
    growable = {
        g.defect_id for g in after.growth if g.defect_class == "crack" and g.length_m >= 0.005
    } & whole
    out |= {
        "matchable": len(both),
        "matched": len(set(matched) & both),
        "new_true": sum(g.new for g in after.growth),
        "grown_true": len(growable & both),
        "grown_found": sum(matched[i]["status"] == "grown" for i in growable & set(matched)),
        "growth_errors_mm": [],
        "width_changes_mm": [],  # (true, measured) per crack
        "area_growth_rel_errors": [],
    }
    out["growth_not_imaged"] = len(set(matched) - whole)
    for i, c in sorted(matched.items()):
        g = growth.get(i)
        if g is None or i not in whole:
            continue
        if g.defect_class == "crack" and c["length_change_mm"] is not None:
            out["growth_errors_mm"].append(round(abs(c["length_change_mm"] - g.length_m * 1000), 2))
            if c.get("width_change_mm") is not None:
                out["width_changes_mm"].append(
                    (round(g.width_m * 1000, 2), round(c["width_change_mm"], 2))
                )
        elif g.defect_class == "corrosion" and c["area_change_mm2"] is not None and g.area_m2 > 0:
            true_mm2 = g.area_m2 * 1e6
            out["area_growth_rel_errors"].append(
                round(abs(c["area_change_mm2"] - true_mm2) / true_mm2, 3)
            )
    return out


def _size(c: dict[str, Any]) -> float:
    return float(c["after"].get("area_mm2") or c["after"].get("length_mm") or 0.0)


def score_condition(
    table: list[dict[str, Any]], elements: list[dict[str, Any]], structure: SteelStructure
) -> dict[str, Any]:
    """The largest difference between the station's and the truth's quantity in any
    condition state of any element, as a fraction of the element's quantity (the truth: the
    structure's true defects coded by the same rules)."""
    els = [Element(i, e["number"], e["quantity"], tuple(e["box"])) for i, e in enumerate(elements)]
    coded: dict[int, list[CodedDefect]] = {e.id: [] for e in els}
    for t in structure.defects:
        where = element_of(_box(t), els)
        if where is not None:
            state = 3 if t.defect_class == "crack" else 2
            code = 1010 if t.defect_class == "crack" else 1000
            coded[where].append(CodedDefect(t.id, _box(t), code, state))
    worst = 0.0  # over the length and area elements
    each_wrong = 0  # "each" elements (gusset plates) in another state than the truth's
    for row, e in zip(table, els, strict=True):
        expected = state_quantities(e, coded[e.id])
        diff = max(abs(row["cs"][f"cs{k}"] - expected[k]) / e.quantity for k in range(1, 5))
        if e.unit == "each":
            each_wrong += diff > 0
        else:
            worst = max(worst, diff)
    return {"condition_error": round(worst, 4), "each_elements_wrong": each_wrong}
