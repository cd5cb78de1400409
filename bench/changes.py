"""``steelscan bench changes``: ``steelscan changes``'s alignment and matching on real crack
photographs. Each pair is made from one photograph of a public dataset
(:mod:`processing.history.pairs`): the far part of its longest crack painted out for BEFORE,
the whole photograph seen again turned (±10°), rescaled (±5 %), shifted and relit for AFTER.

Per dataset: alignment error (mean corner distance to the true homography, px; target 2),
grown cracks found (a grown or new defect where the crack grew; target 90 %), false changes
(defects reported new, gone or grown anywhere else, over all reported changes; target
10 %), and the median growth error of the found ones (target 20 %). A pair whose crack grew
by less than the contract's unchanged tolerance (max(20 px, 10 % of its length)) is truly
``unchanged``: it counts in no found rate, and a growth reported there is a false change.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from bench.common import Result

DATASETS = Path(__file__).resolve().parents[2] / "shared" / "datasets"
SETS = ("deepcrack-train", "cracksc", "uav75", "masonry_dais", "magnetic_tile_crack")
TARGETS = {"align_px": 2.0, "found": 0.9, "false": 0.1, "growth_error": 0.2}


def _overlaps(a: tuple[int, ...], b: tuple[int, ...]) -> bool:
    return (
        a[0] <= b[0] + b[2] and b[0] <= a[0] + a[2] and a[1] <= b[1] + b[3] and b[1] <= a[1] + a[3]
    )


def _pairs(folder: Path, limit: int, rng: np.random.Generator) -> Iterator[object]:
    from processing.history.pairs import make_pair

    images = sorted(
        p
        for p in (folder / "images").iterdir()
        if p.suffix.lower() in {".jpg", ".png", ".jpeg", ".bmp"}
    )
    made = 0
    for path in images[:: max(1, len(images) // (3 * limit))]:
        masks = list((folder / "masks").glob(f"{path.stem}.*"))
        image = cv2.imread(str(path))
        if not masks or image is None:
            continue
        pair = make_pair(image, cv2.imread(str(masks[0]), 0) > 127, rng)
        if pair is not None:
            made += 1
            yield pair
        if made >= limit:
            return


def _score(pair: object, method: str) -> dict[str, float]:
    from processing.history.align import AlignmentError, align_visits
    from processing.history.changes import ChangeParams, compare_visits, crack_evidence
    from processing.history.pairs import VisitPair, corner_error_px

    assert isinstance(pair, VisitPair)
    try:
        al = align_visits(pair.before, pair.after)
    except AlignmentError:
        return {"align_px": float("inf"), "found": 0.0, "false": 0.0, "changes": 0.0}
    h, w = pair.after.shape[:2]
    changes = compare_visits(
        pair.before, pair.after, al, lambda image: crack_evidence(image, method)
    )
    hits = [
        c
        for c in changes
        if c.status in ("grown", "new")
        and c.bbox_after
        and _overlaps(c.bbox_after, pair.grown_box_after)
    ]
    reported = [c for c in changes if c.status != "unchanged"]
    p = ChangeParams()
    grew = pair.growth_px > max(p.unchanged_px, p.unchanged_fraction * pair.length_after_px)
    if not grew:
        hits = []
    out = {
        "align_px": corner_error_px(al.after_to_before, pair.after_to_before, (w, h)),
        "false": float(len([c for c in reported if c not in hits])),
        "changes": float(len(reported)),
    }
    if grew:
        out["found"] = float(bool(hits))
    if hits:
        measured = sum(c.growth_px for c in hits)
        out["growth_error"] = abs(measured - pair.growth_px) / pair.growth_px
    return out


def bench_changes(
    *, dataset: Path | None = None, limit: int | None = None, method: str = "learned"
) -> Iterator[Result]:
    """Per dataset and over all: alignment, grown cracks found, false changes, growth error."""
    rng = np.random.default_rng(2026)
    folders = [dataset] if dataset else [DATASETS / s for s in SETS if (DATASETS / s).is_dir()]
    every: list[dict[str, float]] = []
    for folder in folders:
        scores = [_score(p, method) for p in _pairs(folder, limit or 12, rng)]
        every += scores
        yield from _results(folder.name, scores)
    if len(folders) > 1:
        yield from _results("all", every)


def _results(name: str, scores: list[dict[str, float]]) -> Iterator[Result]:
    if not scores:
        return
    align = [s["align_px"] for s in scores]
    grown = [s["found"] for s in scores if "found" in s]
    found = float(np.mean(grown)) if grown else float("nan")
    changes = sum(s["changes"] for s in scores)
    false = sum(s["false"] for s in scores) / changes if changes else 0.0
    growth = [s["growth_error"] for s in scores if "growth_error" in s]
    values = {
        "align_px": (float(np.median(align)), "px", {"worst": round(max(align), 3)}),
        "found": (found, "fraction", {"grown_pairs": len(grown)}),
        "false": (false, "fraction", {"changes": int(changes)}),
        "growth_error": (
            float(np.median(growth)) if growth else float("nan"),
            "fraction",
            {"worst": round(max(growth), 3) if growth else None},
        ),
    }
    for key, (value, unit, extra) in values.items():
        target = TARGETS[key]
        yield {
            "name": f"changes.{name}.{key}",
            "value": round(value, 4),
            "unit": unit,
            "baseline": target,
            "baseline_is": "target",
            "ratio": round(value / target, 3),
            "pairs": len(scores),
            **extra,
        }
