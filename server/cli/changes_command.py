"""``steelscan changes BEFORE AFTER --out DIR``: a surface's history from two visits' images —
aligned, defects detected in both and matched, each crack's growth measured
(:mod:`processing.history`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from processing.detection import detect_cracks_tiled
from processing.history.align import AlignmentError, align_visits
from processing.history.changes import Change, CrackEvidence, compare_visits, crack_evidence
from server.cli.commands import TILED_ABOVE_PX, read_image
from server.errors import CommandError
from server.storage.files import write_atomic


def _bgr(image: np.ndarray, path: Path) -> np.ndarray:
    if image.dtype != np.uint8:
        raise CommandError(f"{path}: expected an 8-bit image, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 4:
        return image[..., :3]
    return image


def _cracks(image: np.ndarray, method: str) -> CrackEvidence:
    try:
        if method != "learned" and image.shape[0] * image.shape[1] > TILED_ABOVE_PX:
            mask = detect_cracks_tiled(image, method=method)  # type: ignore[arg-type]
            return CrackEvidence(mask, mask)
        return crack_evidence(image, method)
    except (ValueError, FileNotFoundError) as exc:
        raise CommandError(f"crack detection ({method}): {exc}") from None


def _record(change: Change, px_per_mm: float | None) -> dict[str, Any]:
    rec: dict[str, Any] = {
        "id": change.id,
        "status": change.status,
        "bbox_after": list(change.bbox_after) if change.bbox_after else None,
        "bbox_before": list(change.bbox_before) if change.bbox_before else None,
        "length_before_px": change.length_before_px,
        "length_after_px": change.length_after_px,
        "growth_px": round(change.growth_px, 2),
    }
    if px_per_mm:
        for key in ("length_before", "length_after"):
            v = rec[f"{key}_px"]
            rec[f"{key}_mm"] = None if v is None else round(v / px_per_mm, 3)
        rec["growth_mm"] = round(change.growth_px / px_per_mm, 3)
    return rec


def changes(
    before_path: Path, after_path: Path, out: Path, *, method: str, px_per_mm: float | None
) -> None:
    """Write ``alignment.json`` and ``changes.json`` for two visits' images."""
    if px_per_mm is not None and px_per_mm <= 0:
        raise CommandError(f"--px-per-mm must be positive, got {px_per_mm}")
    before = _bgr(read_image(before_path), before_path)
    after = _bgr(read_image(after_path), after_path)
    try:
        alignment = align_visits(before, after)
    except AlignmentError as exc:
        raise CommandError(f"{before_path.name} and {after_path.name}: {exc}") from None
    found = compare_visits(before, after, alignment, lambda image: _cracks(image, method))
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(
        out / "alignment.json",
        json.dumps(
            {
                "after_to_before": np.round(alignment.after_to_before, 10).tolist(),
                "residual_px": round(alignment.residual_px, 4),
                "overlap": round(alignment.overlap, 4),
                "inliers": alignment.inliers,
            },
            indent=1,
        ).encode(),
    )
    write_atomic(
        out / "changes.json", json.dumps([_record(c, px_per_mm) for c in found], indent=1).encode()
    )
