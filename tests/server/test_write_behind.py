"""Large scratch files written behind: the same bytes, sent to the disk as they are written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvips

from server.storage.files import write_atomic
from server.storage.write_behind import STEP_BYTES, WriteBehind, save_behind


def _bytes_sent_to_storage() -> int:
    """This process's bytes submitted to the block device (``write_bytes`` of /proc/self/io)."""
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("write_bytes:"):
            return int(line.split()[1])
    raise AssertionError("no write_bytes in /proc/self/io")


def test_a_file_written_behind_holds_every_byte_in_order(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    data = rng.integers(0, 256, size=3 * STEP_BYTES + 12345, dtype=np.uint8).tobytes()
    path = tmp_path / "scratch.raw"
    with WriteBehind(path, step=STEP_BYTES) as out:
        at = 0
        for size in (1, 4095, STEP_BYTES - 7, 2 * STEP_BYTES, len(data)):  # odd-sized writes
            assert out.write(memoryview(data)[at : at + size]) == len(data[at : at + size])
            at += size
    assert path.read_bytes() == data


def test_the_writer_sends_its_data_to_the_disk_as_it_goes_not_at_the_kernels_leisure(
    tmp_path: Path,
) -> None:
    """Buffered writes leave the pages dirty for the kernel's later writeback; a file written
    behind has been sent to the disk, all but its last steps, by the time it is closed."""
    step = 2 * 2**20
    chunk = np.random.default_rng(4).integers(0, 256, size=step, dtype=np.uint8).tobytes()
    total = 24 * step
    before = _bytes_sent_to_storage()
    with WriteBehind(tmp_path / "behind.raw", step=step) as out:
        for _ in range(total // step):
            out.write(chunk)
    sent = _bytes_sent_to_storage() - before
    assert sent >= total - 2 * step


def test_large_atomic_writes_and_libvips_saves_are_written_behind(tmp_path: Path) -> None:
    data = bytes(range(256)) * (2 * STEP_BYTES // 256 + 3)
    before = _bytes_sent_to_storage()
    write_atomic(tmp_path / "big.bin", data)
    assert _bytes_sent_to_storage() - before >= len(data) - 2 * STEP_BYTES
    assert (tmp_path / "big.bin").read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == ["big.bin"]  # no temporary file left

    image = np.random.default_rng(5).integers(0, 256, size=(300, 400, 3), dtype=np.uint8)
    vips = pyvips.Image.new_from_array(image, interpretation="srgb")
    save_behind(vips, tmp_path / "m.png", ".png", compression=1)
    save_behind(vips, tmp_path / "m.raw", ".raw")
    back = pyvips.Image.new_from_file(str(tmp_path / "m.png")).numpy()
    assert np.array_equal(back, image)
    raw = np.fromfile(tmp_path / "m.raw", dtype=np.uint8).reshape(image.shape)
    assert np.array_equal(raw, image)
