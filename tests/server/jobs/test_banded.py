"""Defect detection band by band with bounded memory: the same defects as one pass over the
mosaic, across band edges, from the station's PNG or another tool's, with the frames'
seams; the pieces a mosaic's PNG is unpacked in (runs of its segments, as many as workers
can share and no more; one piece for a PNG another tool wrote)."""

from __future__ import annotations

import shutil
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from processing.detection import CrackMethod, defect_masks, find_defects
from processing.detection.crack_filter import SurfaceStats, sample_surface
from processing.detection.defects import Defect as Defect_
from processing.detection.surface import on_surface, surface_level
from server.jobs.banded import MAX_PIECES, detect_banded, pieces_of
from server.jobs.context import write_png
from server.storage.png_segments import join_segments, read_rows, write_segment
from tests.conftest import LiveServer


def one_pass(
    source: Path,
    out: Path,
    mm_per_px: float | None,
    method: CrackMethod = "proposed",
    surface: SurfaceStats | None = None,
    threads: int = 2,
) -> list[Defect_]:
    """The reference: defects of a mosaic (in ``source``) found in one pass over it in
    memory, on ``threads``; writes the mask PNGs into ``out``."""
    mosaic = cv2.imread(str(source / "mosaic.png"), cv2.IMREAD_COLOR)
    if mosaic is None:
        raise ValueError("mosaic.png cannot be read")
    coverage = cv2.imread(str(source / "mosaic_coverage.png"), cv2.IMREAD_GRAYSCALE)
    if coverage is None or coverage.shape != mosaic.shape[:2]:
        coverage = np.any(mosaic > 0, axis=2).astype(np.uint8) * 255
    seams = (
        cv2.imread(str(source / "mosaic_seams.png"), cv2.IMREAD_GRAYSCALE)
        if (source / "mosaic_seams.png").is_file()
        else None
    )
    seams = seams > 0 if seams is not None and seams.shape == mosaic.shape[:2] else None
    valid = on_surface(mosaic, coverage)
    cracks, rust, found = find_defects(
        mosaic,
        mm_per_px,
        valid,
        seams,
        workers=threads,
        method=method,
        surface=surface,
        network_threads=threads,
    )
    write_png(out / "crack_mask.png", cracks.astype(np.uint8) * 255)
    write_png(out / "corrosion_mask.png", rust.astype(np.uint8) * 255)
    return found


def test_pieces_are_runs_of_whole_segments_covering_every_row(tmp_path: Path) -> None:
    image = np.random.default_rng(3).integers(0, 255, (150, 40), dtype=np.uint8)
    for y in range(0, 150, 2):  # 75 segments of 2 rows: more than workers could share
        write_segment(tmp_path / "png", y, image[y : y + 2])
    join_segments(tmp_path / "png", tmp_path / "m.png", 40, 150, 1)
    pieces = pieces_of(tmp_path / "m.png", 150)
    assert len(pieces) == MAX_PIECES < 75
    assert pieces[0][0] == 0 and pieces[-1][1] == 150
    assert all(a[1] == b[0] for a, b in zip(pieces, pieces[1:]))  # no gap, no overlap
    assert all(y0 % 2 == 0 and y1 % 2 == 0 for y0, y1 in pieces)  # whole segments
    cv2.imwrite(str(tmp_path / "other.png"), image)
    assert pieces_of(tmp_path / "other.png", 150) == [(0, 150)]


def test_banded_detection_matches_the_one_pass_result(
    inspected: tuple[LiveServer, str], tmp_path: Path
) -> None:
    """Bounded-memory detection (bands of 200 rows, defects crossing seams joined) finds the
    same defects as the in-memory pass on the session's mosaic."""
    live, sid = inspected
    results = tmp_path / "results"
    shutil.copytree(live.settings.data_dir / "sessions" / sid / "results", results)
    mosaic = cv2.imread(str(results / "mosaic.png"), cv2.IMREAD_COLOR)
    surface = sample_surface(mosaic)
    one = one_pass(results, results, 0.25, surface=surface)
    coverage = cv2.imread(str(results / "mosaic_coverage.png"), cv2.IMREAD_GRAYSCALE)
    level = surface_level(mosaic, coverage)
    assert on_surface(mosaic, coverage, level).any()
    masks_of = partial(defect_masks, surface=surface)
    banded = detect_banded(results, results, masks_of, 0.25, level, rows=200)
    assert mosaic.shape[0] > 400  # several bands, so defects cross seams

    def key(d):
        return (d.defect_class, d.bbox)

    assert sorted(map(key, banded)) == sorted(map(key, one))
    by_box = {key(d): d for d in one}
    for d in banded:
        ref = by_box[key(d)]
        assert d.area_px == ref.area_px and abs(d.length_px - ref.length_px) < 1e-6
        assert abs(d.max_width_px - ref.max_width_px) <= 1.0  # contrast kept as whole grey levels
    masks = cv2.imread(str(results / "crack_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert masks.shape == mosaic.shape[:2] and set(np.unique(masks)) <= {0, 255}
    # each band decoded its rows of the station's PNG itself; a PNG from another tool
    # (no segment index) is unpacked first, with the same result
    assert read_rows(results / "mosaic.png", 0, 1) is not None
    cv2.imwrite(str(results / "mosaic.png"), mosaic)
    assert read_rows(results / "mosaic.png", 0, 1) is None
    other = detect_banded(results, results, masks_of, 0.25, level, rows=200)
    assert sorted(map(key, other)) == sorted(map(key, one))
    # the frames' seams, where a crack filter must not answer to an edge between frames
    seams = np.zeros(mosaic.shape[:2], np.uint8)
    seams[:, ::97] = 255
    cv2.imwrite(str(results / "mosaic_seams.png"), seams)
    one = one_pass(results, results, 0.25, surface=surface)
    across = detect_banded(results, results, masks_of, 0.25, level, rows=200)
    assert sorted(map(key, across)) == sorted(map(key, one))


def test_banded_cracks_carry_the_confidence_of_one_pass(
    inspected: tuple[LiveServer, str], tmp_path: Path
) -> None:
    """The network's logits cross band edges as stored codes: each crack's calibrated
    confidence is the one the whole mosaic in memory gives it, to the code's step."""
    from processing.detection.confidence import Calibration
    from processing.detection.defects import measure_defects
    from processing.detection.learned import MODEL_PATH, LearnedParams
    from processing.learning.calibration import store_calibration

    live, sid = inspected
    results = tmp_path / "results"
    shutil.copytree(live.settings.data_dir / "sessions" / sid / "results", results)
    model = tmp_path / "calibrated.onnx"
    shutil.copy(MODEL_PATH, model)
    calibration = Calibration((1.0, 0.5), -3.0)
    store_calibration(model, calibration.to_record())
    mosaic = cv2.imread(str(results / "mosaic.png"), cv2.IMREAD_COLOR)
    coverage = cv2.imread(str(results / "mosaic_coverage.png"), cv2.IMREAD_GRAYSCALE)
    level = surface_level(mosaic, coverage)
    masks_of = partial(
        defect_masks, crack_method="learned", learned_params=LearnedParams(model_path=model)
    )
    whole = masks_of(mosaic, on_surface(mosaic, coverage, level), None)
    assert whole.calibration == calibration
    one = measure_defects(
        whole.cracks,
        "crack",
        components=whole.crack_components,
        probability=whole.probability,
        calibration=whole.calibration,
    )
    banded = [
        d
        for d in detect_banded(
            results, results, masks_of, 0.25, level, rows=200, calibration=calibration
        )
        if d.defect_class == "crack"
    ]
    assert len(one) >= 2 and len(banded) == len(one)

    def overlap(a: Defect_, b: Defect_) -> float:
        (ax, ay, aw, ah), (bx, by, bw, bh) = a.bbox, b.bbox
        w = max(0, min(ax + aw, bx + bw) - max(ax, bx))
        h = max(0, min(ay + ah, by + bh) - max(ay, by))
        return w * h / (aw * ah + bw * bh - w * h)

    # the network sees other tiles in bands: a pixel or two of a box may differ
    for d in banded:
        ref = max(one, key=lambda r: overlap(d, r))
        assert overlap(d, ref) > 0.9
        assert d.confidence is not None and ref.confidence is not None
        assert abs(d.confidence - ref.confidence) < 0.01
