"""The history benchmark's scoring against the simulator's truth: a placement is scored by
the plate's worst corner, detections belong to the true defect they touch, and a pair
across visits is right only when both sides are the same true defect."""

from __future__ import annotations

import types
import uuid

import numpy as np
import pytest

from bench.history_score import (
    VisitTruth,
    mosaic_anchor,
    score_changes,
    score_placement,
    truth_of,
)
from processing.poses import compose_se2, se2_matrix
from robot_link.sim.aging import age_structure
from robot_link.sim.inspection import InspectionSim, SimConfig
from robot_link.sim.structure import make_structure

SMALL = {"plate_size_m": (0.8, 0.5), "defect_region_m": (0.1, 0.1, 0.7, 0.4)}


def _box(t) -> list[float]:  # type: ignore[no-untyped-def]
    x, y, w, h = t.bbox_m
    return [x, y, x + w, y + h]


def test_the_simulated_robot_set_down_off_the_datum_knows_where_its_world_lies() -> None:
    link = types.SimpleNamespace(session_id=uuid.uuid4(), on_command=None)
    offset = (0.02, -0.01, np.radians(2.0))
    sim = InspectionSim(link, SimConfig(start_offset=offset), structure=make_structure(3, **SMALL))  # type: ignore[arg-type]
    # the world's datum composed with the believed start is the true start
    true_start = compose_se2(sim.datum(), sim.robot.odom)
    assert true_start == pytest.approx(sim.robot.pose)
    assert not np.allclose(sim.robot.pose, sim.robot.odom)


def test_a_placement_is_scored_over_the_surface_the_visit_imaged() -> None:
    true = np.array([0.01, 0.0, np.radians(1.0)])  # where the robot truly set its world
    poses = [[0.2, 0.15, 0.0], [1.2, 0.15, 0.0], [1.2, 0.5, np.pi]]  # frames, on the structure
    anchors = (np.eye(3), se2_matrix(*true))  # both mosaics exact in their worlds
    exact = {"datum": {"x": 0.01, "y": 0.0, "yaw": float(true[2])}, "residual_mm": 0.3}
    scored = score_placement(exact, anchors, None, poses)
    assert scored["registration_mm"] == pytest.approx(0.0, abs=1e-6)
    assert scored["absolute_mm"] == pytest.approx(0.0, abs=1e-6)
    # the marked datum is off by the offset: the 10 mm shift and the turn's sweep
    moved = [(np.eye(3) - np.linalg.inv(anchors[1])) @ [p[0], p[1], 1] for p in poses]
    assert scored["marked_mm"] == pytest.approx(max(np.linalg.norm(moved, axis=1)) * 1000, abs=1e-3)
    assert 10 < scored["marked_mm"] < 10 + 1.3 * np.radians(1.0) * 1000
    # the previous visit's mosaic 2 mm off the truth, and placed as it is: this visit agrees
    # with it when it is placed 2 mm off too
    shifted = (se2_matrix(0.002, 0.0, 0.0), anchors[1])
    off = {"datum": {"x": 0.008, "y": 0.0, "yaw": float(true[2])}, "residual_mm": 0.3}
    scored = score_placement(off, shifted, None, poses)
    assert scored["registration_mm"] == pytest.approx(0.0, abs=1e-6)
    assert scored["absolute_mm"] == pytest.approx(2.0)
    assert score_placement(None, anchors, None, poses)["registration_mm"] is None


def test_a_mosaics_anchor_is_the_rigid_fit_of_its_frames_to_the_truth() -> None:
    truth = np.array([[0.2, 0.15, 0.0], [0.8, 0.15, 0.0], [0.8, 0.4, 0.0], [0.3, 0.45, 0.0]])
    T = se2_matrix(0.01, -0.02, 0.03)
    world = np.column_stack([truth[:, :2], np.ones(4)]) @ np.linalg.inv(T).T
    mosaic = {
        "origin_m": [0.1, 0.1],
        "px_per_m": 1000.0,
        "frames": [{"x": (p[0] - 0.1) * 1000, "y": (p[1] - 0.1) * 1000} for p in world],
    }
    assert mosaic_anchor(mosaic, truth) == pytest.approx(T)


def test_pairs_are_right_only_when_both_sides_are_one_true_defect() -> None:
    first = make_structure(3, **SMALL)
    second, growth = age_structure(first, seed=30)
    before, after = VisitTruth(first, [], (0, 0, 0)), VisitTruth(second, growth, (0, 0, 0))
    crack = next(g for g in growth if g.defect_class == "crack")
    tb = {t.id: t for t in first.defects}
    ta = {t.id: t for t in second.defects}
    other = next(i for i in tb if i != crack.defect_id)
    assert truth_of(_box(ta[crack.defect_id]), second.defects) == crack.defect_id
    assert truth_of([0.0, 0.0, 0.001, 0.001], second.defects) is None

    def side(t, length=None):  # type: ignore[no-untyped-def]
        return {"box_m": _box(t), "length_mm": length}

    changes = [
        {  # the grown crack, measured 1 mm long of the truth
            "status": "grown",
            "before": side(tb[crack.defect_id]),
            "after": side(ta[crack.defect_id]),
            "length_change_mm": crack.length_m * 1000 - 1.0,
            "area_change_mm2": None,
        },
        {  # two different defects paired: a false match
            "status": "unchanged",
            "before": side(tb[other]),
            "after": side(ta[next(i for i in ta if i not in (other, crack.defect_id))]),
            "length_change_mm": 0.0,
            "area_change_mm2": None,
        },
    ]
    s = score_changes(changes, before, after)
    assert s["matched"] == 1 and s["false_matches"] == 1
    assert s["growth_errors_mm"] == [pytest.approx(1.0)]
    assert s["grown_found"] == (1 if crack.length_m >= 0.005 else 0)
