"""``steelscan changes`` as a user runs it, on two visits made from a real crack photograph:
the alignment and the changes written as the contract says; bad input refused with one
error line and no changes.json."""

import json
from pathlib import Path

import cv2
import numpy as np

from processing.history.pairs import corner_error_px, make_pair
from tests.server.helpers import assert_clean_error, steelscan

DATASET = Path(__file__).resolve().parents[4] / "shared" / "datasets" / "deepcrack-train"


def _pair(tmp_path: Path, stem: str = "11111", seed: int = 1):  # type: ignore[no-untyped-def]
    image = cv2.imread(str(DATASET / "images" / f"{stem}.jpg"))
    mask = cv2.imread(str(DATASET / "masks" / f"{stem}.png"), 0) > 127
    pair = make_pair(image, mask, np.random.default_rng(seed))
    assert pair is not None
    cv2.imwrite(str(tmp_path / "before.png"), pair.before)
    cv2.imwrite(str(tmp_path / "after.jpg"), pair.after, [cv2.IMWRITE_JPEG_QUALITY, 92])
    return pair


def test_a_grown_crack_is_found_and_measured(tmp_path: Path) -> None:
    pair = _pair(tmp_path)
    out = tmp_path / "out"
    proc = steelscan(
        "changes",
        str(tmp_path / "before.png"),
        str(tmp_path / "after.jpg"),
        "--out",
        str(out),
        "--px-per-mm",
        "4",
    )
    assert proc.returncode == 0, proc.stderr
    alignment = json.loads((out / "alignment.json").read_text())
    H = np.array(alignment["after_to_before"])
    assert H.shape == (3, 3)
    assert corner_error_px(H, pair.after_to_before, pair.after.shape[1::-1]) < 1.0
    assert alignment["residual_px"] >= 0 and 0.5 <= alignment["overlap"] <= 1.0
    changes = json.loads((out / "changes.json").read_text())
    keys = {
        "id",
        "status",
        "bbox_after",
        "bbox_before",
        "length_before_px",
        "length_after_px",
        "growth_px",
        "length_before_mm",
        "length_after_mm",
        "growth_mm",
    }
    assert all(keys <= set(c) for c in changes)
    assert {c["status"] for c in changes} <= {"new", "gone", "unchanged", "grown"}
    x, y, w, h = pair.grown_box_after
    grown = [c for c in changes if c["status"] == "grown"]
    assert len(grown) == 1
    bx, by, bw, bh = grown[0]["bbox_after"]
    assert bx <= x + w and x <= bx + bw and by <= y + h and y <= by + bh  # where it grew
    assert abs(grown[0]["growth_px"] - pair.growth_px) < 0.5 * pair.growth_px
    assert grown[0]["growth_mm"] == round(grown[0]["growth_px"] / 4, 3)


def test_images_of_different_surfaces_or_unreadable_ones_are_refused(tmp_path: Path) -> None:
    _pair(tmp_path)
    other = cv2.imread(str(sorted((DATASET / "images").glob("*.jpg"))[200]))
    cv2.imwrite(str(tmp_path / "other.png"), cv2.flip(other, -1))
    out = tmp_path / "out"
    proc = steelscan(
        "changes", str(tmp_path / "before.png"), str(tmp_path / "other.png"), "--out", str(out)
    )
    assert_clean_error(proc, "other.png")
    assert not (out / "changes.json").exists()
    (tmp_path / "broken.png").write_bytes(b"not an image")
    proc = steelscan(
        "changes", str(tmp_path / "before.png"), str(tmp_path / "broken.png"), "--out", str(out)
    )
    assert_clean_error(proc, "broken.png")
    assert not (out / "changes.json").exists()
