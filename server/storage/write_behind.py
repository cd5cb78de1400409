"""Large files written without a flood of dirty pages: write-behind.

A buffered write only copies into the page cache; the kernel writes the pages back later,
hundreds of megabytes at a time when a job writes a mosaic's scratch. On ext4 (ordered
data) every other writer of the same disk then waits behind that writeback for its
journal, however small its own write: the live link's frame stores and database commits
stalled 40-70 ms while a job wrote 400 MB, against 2 ms quiet (``docs/benchmarks.md``).

:class:`WriteBehind` writes back its file as it goes, ``step`` bytes at a time
(``sync_file_range``: start writing the step just written, wait for the one before), so a
writer holds at most two steps of dirty pages whatever the file's size. This is not a
flush to stable storage (no fsync: the journal is not forced); it paces the writer to the
disk. Where ``sync_file_range`` does not exist (not Linux) it is a plain buffered file.

Each system call moves at most :data:`CALL_BYTES`. A kernel built without preemption
(``PREEMPT_NONE``, the server default of many distributions) does not take the CPU from a
task inside a system call: a worker at idle priority copying 8 MB into the page cache in
one ``write`` holds its core for milliseconds while the station's live link waits to run.
Beside two processes writing 50 MB/s between them, the live link's ACK p99 was 9.6-17.1 ms
in 8 MB calls and 3.6-5.3 ms in 64 kB calls, against 3.2-6.1 ms with nothing beside it
(``docs/benchmarks.md``, scale-out). Large reads go the same way (:func:`read_up_to`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

import pyvips

STEP_BYTES = 8 * 2**20
# one system call's copy: about 0.2 ms at the page cache's 1-1.5 GB/s a core, far below
# the scheduling latency the live link is measured at
CALL_BYTES = 256 * 2**10

_WAIT_BEFORE, _WRITE, _WAIT_AFTER = 1, 2, 4  # SYNC_FILE_RANGE_* of <fcntl.h>


def _sync_file_range() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    try:
        fn = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).sync_file_range
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_longlong, ctypes.c_longlong, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_SYNC_FILE_RANGE = _sync_file_range()


class WriteBehind:
    """A binary file opened for writing (created or truncated) that keeps at most two
    ``step``-byte ranges of its pages dirty: a context manager with ``write`` and ``close``."""

    def __init__(self, path: Path | str, step: int = STEP_BYTES) -> None:
        self.path, self.step = Path(path), step
        self._fh = open(path, "wb", buffering=0)  # noqa: SIM115 (closed by close())
        self._written = 0  # bytes written so far
        self._started = 0  # bytes whose writeback has been started

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        size = view.nbytes
        while view:
            n = self._fh.write(view[:CALL_BYTES])
            assert n is not None
            view = view[n:]
            self._written += n
            if self._written - self._started >= self.step:
                self._behind()
        return size

    def _behind(self) -> None:
        """Start writing back what is new; wait for the step before it."""
        if _SYNC_FILE_RANGE is None:
            return
        fd, start, end = self._fh.fileno(), self._started, self._written
        _SYNC_FILE_RANGE(fd, start, end - start, _WRITE)
        if start >= self.step:
            _SYNC_FILE_RANGE(fd, start - self.step, self.step, _WAIT_BEFORE | _WRITE | _WAIT_AFTER)
        self._started = end

    def fileno(self) -> int:
        return self._fh.fileno()

    def close(self) -> None:
        """Close the file; the writeback of its tail is started when it was written behind
        at all (a file under one step is left to the kernel, as any small file)."""
        if not self._fh.closed:
            if self._started:
                self._behind()
            self._fh.close()

    def __enter__(self) -> WriteBehind:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_up_to(fh: BinaryIO, size: int) -> bytes:
    """Up to ``size`` bytes from ``fh``'s position (fewer at the file's end), read in system
    calls of at most :data:`CALL_BYTES`."""
    out = bytearray(size)
    view, done = memoryview(out), 0
    while done < size:
        n = fh.readinto(view[done : done + CALL_BYTES])
        if not n:
            break
        done += n
    return bytes(view[:done])


def vips_target(out: WriteBehind) -> pyvips.TargetCustom:
    """A libvips target that writes through ``out`` (for ``*save_target``)."""
    target = pyvips.TargetCustom()
    target.on_write(out.write)
    return target


def save_behind(image: pyvips.Image, path: Path, suffix: str, **options: object) -> None:
    """``image`` saved by libvips in the format of ``suffix`` (".png", ".raw", ...) to
    ``path``, written behind."""
    with WriteBehind(path) as out:
        if suffix == ".raw":
            image.rawsave_target(vips_target(out))
        else:
            image.write_to_target(vips_target(out), suffix, **options)


def write_file_behind(path: Path, data: bytes | memoryview) -> None:
    """``data`` written to ``path`` behind (large scratch files)."""
    with WriteBehind(path) as out:
        out.write(data)
