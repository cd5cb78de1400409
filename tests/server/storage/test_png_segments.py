"""A PNG encoded in segments of rows on their own and joined: the same pixels as the image,
read by OpenCV and libvips, whatever order the segments were written in; any run of its
rows decoded from the PNG alone."""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import pyvips

from robot_link.sim.sweeps import LazySweep, SweepConfig
from server.storage.png_segments import (
    adler32_combine,
    join_segments,
    read_rows,
    segment_rows,
    sub_filtered,
    write_segment,
)


def _painted_steel() -> np.ndarray:
    """Four frames of the simulator's painted steel side by side, RGB (240, 1280, 3)."""
    sweep = LazySweep(SweepConfig(frames=4, frame_size=(320, 240), seed=5))
    return cv2.cvtColor(np.hstack([sweep[k] for k in range(4)]), cv2.COLOR_BGR2RGB)


def _write_shuffled(folder: Path, image: np.ndarray, cuts: list[int], seed: int) -> None:
    parts = list(zip(cuts[:-1], cuts[1:]))
    for k in np.random.default_rng(seed).permutation(len(parts)):
        y0, y1 = parts[k]
        write_segment(folder, y0, image[y0:y1])


def _read_vips(path: Path) -> np.ndarray:
    img = pyvips.Image.new_from_file(str(path))
    return np.ndarray(
        buffer=img.write_to_memory(), dtype=np.uint8, shape=(img.height, img.width, img.bands)
    )


def test_segments_written_in_any_order_join_into_the_image(tmp_path: Path) -> None:
    image = _painted_steel()
    cuts = [0, 1, 37, 38, 120, 200, 240]  # one-row segments too
    _write_shuffled(tmp_path / "png", image, cuts, seed=1)
    join_segments(tmp_path / "png", tmp_path / "m.png", 1280, 240, 3)
    read = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(cv2.cvtColor(read, cv2.COLOR_BGR2RGB), image)
    assert np.array_equal(_read_vips(tmp_path / "m.png"), image)
    # smaller than the same image through libvips as the mosaic was saved before
    pyvips.Image.new_from_array(image).copy(interpretation="srgb").pngsave(
        str(tmp_path / "vips.png"), compression=3
    )
    assert (tmp_path / "m.png").stat().st_size < (tmp_path / "vips.png").stat().st_size


def test_grey_images_and_a_segment_written_twice(tmp_path: Path) -> None:
    grey = cv2.cvtColor(_painted_steel(), cv2.COLOR_RGB2GRAY)[:100, :333]
    _write_shuffled(tmp_path / "png", grey, [0, 50, 100], seed=2)
    write_segment(tmp_path / "png", 50, grey[50:100])  # a part run again replaces its segment
    assert not list((tmp_path / "png").glob(".*"))
    join_segments(tmp_path / "png", tmp_path / "g.png", 333, 100, 1)
    assert np.array_equal(cv2.imread(str(tmp_path / "g.png"), cv2.IMREAD_UNCHANGED), grey)


def test_missing_or_extra_rows_are_refused_and_nothing_is_written(tmp_path: Path) -> None:
    image = _painted_steel()
    write_segment(tmp_path / "png", 0, image[:100])
    write_segment(tmp_path / "png", 140, image[140:])
    with pytest.raises(ValueError, match="rows 100-139 missing"):
        join_segments(tmp_path / "png", tmp_path / "m.png", 1280, 240, 3)
    write_segment(tmp_path / "png", 100, image[100:140])
    with pytest.raises(ValueError, match="hold 240 rows, the image has 250"):
        join_segments(tmp_path / "png", tmp_path / "m.png", 1280, 250, 3)
    assert not (tmp_path / "m.png").exists()


def test_adler32_of_a_whole_from_its_parts() -> None:
    rng = np.random.default_rng(7)
    for sizes in ((0, 5), (1, 1), (70000, 3), (5, 200000), (65521, 65521)):
        a, b = (rng.integers(0, 256, n, dtype=np.uint8).tobytes() for n in sizes)
        assert adler32_combine(zlib.adler32(a), zlib.adler32(b), len(b)) == zlib.adler32(a + b)


def test_sub_filter_is_the_difference_to_the_pixel_on_the_left() -> None:
    rows = np.array([[[10, 20, 30], [5, 25, 255], [0, 0, 0]]], np.uint8)
    assert sub_filtered(rows).tolist() == [[1, 10, 20, 30, 251, 5, 225, 251, 231, 1]]


def test_any_rows_are_decoded_from_their_segments_alone(tmp_path: Path) -> None:
    image = _painted_steel()
    _write_shuffled(tmp_path / "png", image, [0, 1, 37, 38, 120, 200, 240], seed=3)
    join_segments(tmp_path / "png", tmp_path / "m.png", 1280, 240, 3)
    cuts = [0, 1, 37, 38, 120, 200, 240]
    assert segment_rows(tmp_path / "m.png") == list(zip(cuts[:-1], cuts[1:]))
    for y0, y1 in ((0, 240), (0, 1), (37, 38), (30, 130), (199, 201), (239, 999), (5, 5)):
        assert np.array_equal(read_rows(tmp_path / "m.png", y0, y1), image[y0:y1])
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    _write_shuffled(tmp_path / "grey", grey, [0, 100, 240], seed=4)
    join_segments(tmp_path / "grey", tmp_path / "g.png", 1280, 240, 1)
    assert np.array_equal(read_rows(tmp_path / "g.png", 90, 110), grey[90:110])
    # another tool's PNG has no segment index: the caller decodes it whole
    cv2.imwrite(str(tmp_path / "other.png"), grey)
    assert read_rows(tmp_path / "other.png", 0, 10) is None
    assert segment_rows(tmp_path / "other.png") is None
    (tmp_path / "short.png").write_bytes(b"\x89PNG")
    assert read_rows(tmp_path / "short.png", 0, 10) is None


def test_a_damaged_segment_is_named_not_decoded(tmp_path: Path) -> None:
    image = _painted_steel()
    _write_shuffled(tmp_path / "png", image, [0, 100, 240], seed=5)
    join_segments(tmp_path / "png", tmp_path / "m.png", 1280, 240, 3)
    data = bytearray((tmp_path / "m.png").read_bytes())
    data[-200] ^= 0x40  # a byte of the last segment's image data
    (tmp_path / "m.png").write_bytes(bytes(data))
    assert np.array_equal(read_rows(tmp_path / "m.png", 0, 100), image[:100])
    with pytest.raises(ValueError, match="rows 100-239 is damaged"):
        read_rows(tmp_path / "m.png", 90, 110)
