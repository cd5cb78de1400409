"""``steelscan bench history``: a structure inspected two and three times, each visit a
simulated robot streaming to a station that stitches, detects and places the visit on the
structure by registering its mosaic to the previous visit's.

Between visits (:func:`robot_link.sim.aging.age_structure`) every crack grows at a tip by
5-30 mm, every rust patch grows and a new one appears, the paint weathers and the light
changes; the robot is set down off the structure's datum by up to 3 cm and 2.5°. Scored
against the simulator's truth, per held-back seed:

- registration error (mm): the largest distance over the plate between where the station
  places a visit's surface and where it truly is (target 2); baseline: the datum as marked;
- defects matched across visits (target 95 %) and false matches (target 0);
- crack growth ≥ 5 mm detected as grown, and its length error (target 2 mm);
- the element condition table (AASHTO CS1-CS4 quantities) against the truth's.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.common import Result, follow_job
from bench.history_score import (
    VisitTruth,
    mosaic_anchor,
    score_changes,
    score_condition,
    score_placement,
)
from robot_link.sim.sensors import DownwardCamera

log = logging.getLogger(__name__)

SEEDS = tuple(range(9101, 9111))
THREE_VISITS = 3  # the first seeds get a third visit
ELEMENTS = [  # the simulated plate girder's panel, 1.6 m x 0.9 m
    {"number": 107, "quantity": 1.6, "box": [0.0, 0.0, 1.6, 0.45]},
    {"number": 162, "quantity": 1.0, "box": [0.6, 0.45, 1.0, 0.9]},
    {"number": 515, "quantity": 1.44, "box": [0.0, 0.0, 1.6, 0.9]},
]
DEFECT_REGION_M = (0.25, 0.14, 1.35, 0.54)  # where make_structure puts defects: the route's
FOOTPRINT_M = DownwardCamera().footprint_m
TARGETS = {"registration_mm": 2.0, "matched": 0.95, "growth_mm": 2.0}


def _visits(seed: int, count: int) -> list[VisitTruth]:
    """The structure at each visit, the growth since the one before, and where the robot
    was set down (the first visit on the datum)."""
    from robot_link.sim.aging import age_structure
    from robot_link.sim.structure import make_structure

    rng = np.random.default_rng(seed)
    out = [VisitTruth(make_structure(seed, defect_region_m=DEFECT_REGION_M), [], (0.0, 0.0, 0.0))]
    for v in range(1, count):
        aged, growth = age_structure(
            out[-1].structure, seed * 10 + v, weathering=0.15, region_m=DEFECT_REGION_M
        )
        offset = (*rng.uniform(-0.03, 0.03, 2), float(np.radians(rng.uniform(-2.5, 2.5))))
        out.append(VisitTruth(aged, growth, (float(offset[0]), float(offset[1]), offset[2])))
    return out


async def _inspect(
    url: str, token: str, visit: VisitTruth, seed: int
) -> tuple[str, list[list[float]]]:
    from robot_link.client import RobotLink
    from robot_link.sim.inspection import InspectionSim, SimConfig

    link = RobotLink(url, token)
    await link.start()
    try:
        config = SimConfig(seed=seed, time_scale=0, start_offset=visit.start_offset)
        sim = InspectionSim(link, config, structure=visit.structure)
        result = await sim.run()
        return result.session_id, result.frame_poses_true
    finally:
        await link.close()


def _process(client: httpx.Client, sid: str) -> None:
    """Stitch, detect on the mosaic and map, as an operator would start them."""
    for kind in ("stitch", "detect", "map"):
        r = client.post(f"/api/sessions/{sid}/jobs", json={"kind": kind})
        follow_job(client, r.raise_for_status().json()["id"], 1.0)


def _run_seed(client: httpx.Client, url: str, token: str, seed: int, count: int) -> dict[str, Any]:
    visits = _visits(seed, count)
    st = client.post("/api/structures", json={"name": f"bench girder {seed}-{time.time()}"})
    structure_id = st.raise_for_status().json()["id"]
    for e in ELEMENTS:
        client.post(f"/api/structures/{structure_id}/elements", json=e).raise_for_status()
    scores: dict[str, Any] = {"seed": seed, "visits": []}
    anchors: list[np.ndarray] = []
    poses: list[list[list[float]]] = []  # each visit's true camera poses
    placed: dict[str, Any] | None = None  # the previous visit's place on the structure
    for v, visit in enumerate(visits):
        t0 = time.monotonic()
        sid, true_poses = asyncio.run(_inspect(url, token, visit, seed * 10 + v))
        _process(client, sid)
        client.put(
            f"/api/sessions/{sid}/structure",
            json={"structure_id": structure_id, "datum": {"x": 0.0, "y": 0.0, "yaw": 0.0}},
        ).raise_for_status()
        world = client.get(f"/api/sessions/{sid}/results/mosaic.json").json()
        anchors.append(mosaic_anchor(world, true_poses))
        poses.append(true_poses)
        record: dict[str, Any] = {"visit": v + 1, "session_id": sid}
        if v > 0:
            changes = client.get(f"/api/sessions/{sid}/changes", timeout=120).json()
            reg = changes["registration"]
            record |= score_placement(reg, (anchors[-2], anchors[-1]), placed, true_poses)
            record["map"] = reg.get("map") if reg else None
            seen = (poses[-2], poses[-1])
            record |= score_changes(changes["changes"], visits[v - 1], visit, seen, FOOTPRINT_M)
            placed = reg["datum"] if reg else None
        condition = client.get(
            f"/api/structures/{structure_id}/condition", params={"session_id": sid}
        ).json()
        record |= score_condition(condition["elements"], ELEMENTS, visit.structure)
        record["seconds"] = round(time.monotonic() - t0, 1)
        log.info("history seed %d visit %d: %s", seed, v + 1, record)
        scores["visits"].append(record)
    return scores


def bench_history(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Visits of ``limit`` held-back seeds (all 10 by default) through one station."""
    from bench.robot import scratch_station

    seeds = SEEDS[: limit or len(SEEDS)]
    _, server, token = scratch_station("history")
    per_seed = []
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            for i, seed in enumerate(seeds):
                per_seed.append(
                    _run_seed(client, server.url, token, seed, 3 if i < THREE_VISITS else 2)
                )
    finally:
        server.stop()
    yield from summarise(per_seed)


def summarise(per_seed: list[dict[str, Any]]) -> Iterator[Result]:
    """The benchmark's result lines from each seed's visit records."""
    later = [(s["seed"], r) for s in per_seed for r in s["visits"] if r["visit"] > 1]
    reg = [r["registration_mm"] for _, r in later if r.get("registration_mm") is not None]
    marked = [r["marked_mm"] for _, r in later]
    failed = sum(r.get("registration_mm") is None for _, r in later)
    yield {
        "name": "history.registration_error_mm",
        "value": round(max(reg), 2) if reg else None,
        "unit": "mm",
        "target": TARGETS["registration_mm"],
        "mean": round(float(np.mean(reg)), 2) if reg else None,
        "baseline": round(max(marked), 1),
        "baseline_is": "the datum as marked (robot set down up to 3 cm, 2.5° off)",
        "not_registered": failed,
        "per_visit": {f"{s}/{r['visit']}": r.get("registration_mm") for s, r in later},
    }
    maps = [r["map"] for _, r in later if r.get("map")]
    yield {
        "name": "history.map_agreement_mm",
        "value": round(max(m["rmse_mm"] for m in maps), 2) if maps else None,
        "unit": "mm",
        "of": "the largest RMS distance across the surfaces between two visits' 3D maps",
        "aligned": f"{len(maps)}/{len(later)}",
        "correction_mm_worst": round(max(m["correction_mm"] for m in maps), 2) if maps else None,
        "height_mm_worst": round(max(abs(m["height_mm"]) for m in maps), 2) if maps else None,
        "tilt_deg_worst": round(max(m["tilt_deg"] for m in maps), 3) if maps else None,
        "truth": "the visits' maps lie on one plate: height and tilt 0",
    }
    matchable = sum(r["matchable"] for _, r in later)
    correct = sum(r["matched"] for _, r in later)
    yield {
        "name": "history.matched",
        "value": round(correct / matchable, 3) if matchable else None,
        "unit": "fraction",
        "target": TARGETS["matched"],
        "false_matches": sum(r["false_matches"] for _, r in later),
        "pairs": matchable,
        "worst_visit": min(
            (r["matched"] / r["matchable"] for _, r in later if r["matchable"]), default=None
        ),
        "new_rust_found": f"{sum(r['new_found'] for _, r in later)}/{sum(r['new_true'] for _, r in later)}",
        "false_changes": sum(r["false_changes"] for _, r in later),
    }
    errors = [e for _, r in later for e in r["growth_errors_mm"]]
    grown = sum(r["grown_found"] for _, r in later)
    growable = sum(r["grown_true"] for _, r in later)
    yield {
        "name": "history.crack_growth_error_mm",
        "value": round(float(np.median(errors)), 2) if errors else None,
        "unit": "mm",
        "target": TARGETS["growth_mm"],
        "p90": round(float(np.percentile(errors, 90)), 2) if errors else None,
        "worst": round(max(errors), 2) if errors else None,
        "within_target": round(float(np.mean(np.array(errors) <= TARGETS["growth_mm"])), 3)
        if errors
        else None,
        "grown_detected": f"{grown}/{growable}",
        "grown_detected_fraction": round(grown / growable, 3) if growable else None,
        "not_imaged_whole": sum(r["growth_not_imaged"] for _, r in later),
    }
    widths = [w for _, r in later for w in r["width_changes_mm"]]
    wider = [m for t, m in widths if t > 0]
    same = [m for t, m in widths if t == 0]
    yield {
        "name": "history.crack_width_change_error_mm",
        "value": round(float(np.median([abs(m - t) for t, m in widths])), 3) if widths else None,
        "unit": "mm",
        "worst": round(max(abs(m - t) for t, m in widths), 3) if widths else None,
        "true_widening_mm": round(max(t for t, _ in widths), 2) if widths else None,
        "measured_on_widened_mm": round(float(np.median(wider)), 3) if wider else None,
        "measured_on_unchanged_mm": round(float(np.median(same)), 3) if same else None,
        "cracks": len(widths),
    }
    area = [e for _, r in later for e in r["area_growth_rel_errors"]]
    yield {
        "name": "history.rust_growth_error",
        "value": round(float(np.median(area)), 3) if area else None,
        "unit": "fraction",
        "worst": round(max(area), 3) if area else None,
    }
    cs = [r["condition_error"] for s in per_seed for r in s["visits"]]
    yield {
        "name": "history.condition_error",
        "value": round(max(cs), 3),
        "unit": "fraction of the element's quantity",
        "of": "the largest CS quantity error of a length or area element",
        "mean": round(float(np.mean(cs)), 3),
        "per_visit": {
            f"{s['seed']}/{r['visit']}": r["condition_error"] for s in per_seed for r in s["visits"]
        },
    }
