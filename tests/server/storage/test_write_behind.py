"""Large scratch files written behind: the same bytes, sent to the disk as they are written."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyvips

from server.storage.files import write_atomic
from server.storage.write_behind import (
    CALL_BYTES,
    STEP_BYTES,
    WriteBehind,
    read_up_to,
    save_behind,
)


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


class _Recording:
    """A raw file that records the size of every system call made through it."""

    def __init__(self, raw: Any) -> None:
        self.raw, self.calls = raw, []  # type: ignore[var-annotated]

    def write(self, data: memoryview) -> int:
        self.calls.append(len(data))
        return self.raw.write(data)

    def readinto(self, buffer: memoryview) -> int:
        self.calls.append(len(buffer))
        return self.raw.readinto(buffer)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.raw, name)


def test_no_system_call_copies_more_than_a_short_call(tmp_path: Path) -> None:
    """A worker inside one long copy holds its core on a kernel without preemption: large
    writes and reads go in calls of at most CALL_BYTES, every byte in order."""
    data = np.random.default_rng(6).integers(0, 256, size=5 * CALL_BYTES + 99, dtype=np.uint8)
    out = WriteBehind(tmp_path / "big.raw")
    out._fh = recorded = _Recording(out._fh)  # type: ignore[assignment]
    with out:
        out.write(data.tobytes())
    assert max(recorded.calls) <= CALL_BYTES and sum(recorded.calls) == data.size
    with (tmp_path / "big.raw").open("rb", buffering=0) as fh:
        reader = _Recording(fh)
        reader.seek(7)
        back = read_up_to(reader, data.size)  # type: ignore[arg-type]
    assert back == data.tobytes()[7:]  # fewer bytes at the file's end
    assert max(reader.calls) <= CALL_BYTES
