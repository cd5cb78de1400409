"""Where a session's files live under the data directory, and how they are written."""

from __future__ import annotations

import os
import tempfile
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any, BinaryIO

from server.storage.write_behind import WriteBehind, read_up_to

SEGMENT_BYTES = 512 * 2**20  # payload segment files are closed and a new one started beyond this
MAX_OPEN_SEGMENTS = 64  # segment files kept open at once, over all sessions


class SessionFiles:
    """Paths of one data directory; everything stored in the DB is relative to it."""

    def __init__(
        self,
        data_dir: Path,
        *,
        fsync: bool = False,
        segment_bytes: int = SEGMENT_BYTES,
        max_open: int = MAX_OPEN_SEGMENTS,
    ) -> None:
        self.data_dir = data_dir.resolve()
        self.fsync = fsync
        self.segment_bytes = segment_bytes
        self.max_open = max_open
        # (session, kind) -> (number, open file), least recently appended to first: beyond
        # ``max_open`` the first is closed, and opened again at its next append
        self._segments: OrderedDict[tuple[str, str], tuple[int, BinaryIO]] = OrderedDict()
        self._numbers: dict[tuple[str, str], int] = {}  # the segment each (session, kind) is at
        self._last_append: dict[str, float] = {}  # session -> time.monotonic() of its last append

    def session_dir(self, session_id: str) -> Path:
        """Folder of one session."""
        return self.data_dir / "sessions" / session_id

    def frame_relpath(self, session_id: str, seq: int) -> str:
        """Relative path of a camera frame."""
        return f"sessions/{session_id}/frames/{seq:010d}.jpg"

    def cloud_relpath(self, session_id: str, seq: int, encoding: str) -> str:
        """Relative path of a ToF cloud payload (depth PNG or raw xyz)."""
        ext = "png" if encoding == "png16_depth_mm" else "xyz"
        return f"sessions/{session_id}/clouds/{seq:010d}.{ext}"

    def append(self, session_id: str, kind: str, data: bytes) -> tuple[str, int]:
        """Append a payload (``kind``: frames or clouds) to the session's current segment file;
        its relative path and byte offset. One file for many payloads: creating a file per
        frame is what limits a disk's ingest rate. The row that points at it is committed
        after it, so a torn append is never read, and a resend appends again. Called by the
        one ingest writer thread."""
        key = (session_id, kind)
        number, fh = self._segments.get(key, (self._numbers.get(key, 0), None))  # type: ignore[arg-type]
        if fh is not None and fh.tell() + len(data) > self.segment_bytes:
            fh.close()
            del self._segments[key]
            number, fh = number + 1, None
        if fh is None:
            folder = self.session_dir(session_id) / kind
            folder.mkdir(parents=True, exist_ok=True)
            while (folder / f"segment-{number:05d}.bin").is_file() and (
                folder / f"segment-{number:05d}.bin"
            ).stat().st_size + len(data) > self.segment_bytes:
                number += 1
            while len(self._segments) >= self.max_open:  # the least recently used gives way
                self._segments.popitem(last=False)[1][1].close()
            # kept open across appends
            fh = open(folder / f"segment-{number:05d}.bin", "ab")  # noqa: SIM115
            self._segments[key] = (number, fh)
            self._numbers[key] = number
        self._segments.move_to_end(key)
        self._last_append[session_id] = time.monotonic()
        offset = fh.seek(0, os.SEEK_END)
        fh.write(data)
        fh.flush()
        if self.fsync:
            os.fsync(fh.fileno())
        return f"sessions/{session_id}/{kind}/segment-{number:05d}.bin", offset

    def close_session(self, session_id: str) -> None:
        """Close the session's open segment files (it ended, or went quiet)."""
        for key in [k for k in self._segments if k[0] == session_id]:
            self._segments.pop(key)[1].close()
        for key in [k for k in self._numbers if k[0] == session_id]:
            del self._numbers[key]
        self._last_append.pop(session_id, None)

    @property
    def open_files(self) -> int:
        """Segment files open now (at most ``max_open``)."""
        return len(self._segments)

    def quiet_sessions(self, idle_s: float) -> list[str]:
        """Sessions with open segment files and no append for ``idle_s`` seconds."""
        cutoff = time.monotonic() - idle_s
        return [sid for sid, t in self._last_append.items() if t < cutoff]

    def read(self, relpath: str, offset: int | None, size: int) -> bytes:
        """A stored payload: ``size`` bytes at ``offset`` of a segment file, or a whole file
        when ``offset`` is None. OSError when it is gone or short."""
        path = self.resolve(relpath)
        with path.open("rb", buffering=0) as fh:
            if offset is None:
                return read_up_to(fh, os.fstat(fh.fileno()).st_size)
            fh.seek(offset)
            data = read_up_to(fh, size)
        if len(data) != size:
            raise OSError(f"{path.name} holds {len(data)} of the {size} bytes at {offset}")
        return data

    def payload(self, row: Any) -> bytes:
        """The stored payload of a frame or cloud row."""
        return self.read(row.path, row.data_offset, row.size_bytes)

    def results_dir(self, session_id: str) -> Path:
        """Folder of a session's processing results."""
        return self.session_dir(session_id) / "results"

    def resolve(self, relpath: str) -> Path:
        """Absolute path of a stored relative path, refusing anything outside the data dir."""
        path = (self.data_dir / relpath).resolve()
        if not path.is_relative_to(self.data_dir):
            raise ValueError(f"path {relpath!r} leaves the data directory")
        return path

    def write(self, relpath: str, data: bytes) -> Path:
        """Write a file atomically (temp file + rename), fsync'd when configured. The path
        is checked by its parts (no symlink resolution on this hot path: the relative paths
        written are the station's own)."""
        parts = Path(relpath).parts
        if not parts or Path(relpath).is_absolute() or ".." in parts:
            raise ValueError(f"path {relpath!r} leaves the data directory")
        return write_atomic(self.data_dir / relpath, data, fsync=self.fsync)


def write_atomic(path: Path, data: bytes, *, fsync: bool = False) -> Path:
    """Write ``data`` to ``path`` so readers never see a half-written file (large data
    written behind: :mod:`server.storage.write_behind`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=path.suffix)
    os.close(fd)
    try:
        with WriteBehind(tmp) as fh:  # a large file is written back as it is written
            fh.write(data)
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
