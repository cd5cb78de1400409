"""Where a session's files live under the data directory, and how they are written."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


class SessionFiles:
    """Paths of one data directory; everything stored in the DB is relative to it."""

    def __init__(self, data_dir: Path, *, fsync: bool = False) -> None:
        self.data_dir = data_dir.resolve()
        self.fsync = fsync
        self._made: set[Path] = set()  # folders known to exist (the ingest path writes many files per folder)

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


    def write_in_place(self, relpath: str, data: bytes) -> Path:
        """Write a file under its final name (no temporary file): for files that a database
        row committed afterwards makes visible, so a torn write is never read and is
        rewritten by the resend. Checked by its parts like :meth:`write`."""
        parts = Path(relpath).parts
        if not parts or Path(relpath).is_absolute() or ".." in parts:
            raise ValueError(f"path {relpath!r} leaves the data directory")
        path = self.data_dir / relpath
        if path.parent not in self._made:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._made.add(path.parent)
        with open(path, "wb") as fh:
            fh.write(data)
            if self.fsync:
                fh.flush()
                os.fsync(fh.fileno())
        return path


def write_atomic(path: Path, data: bytes, *, fsync: bool = False) -> Path:
    """Write ``data`` to ``path`` so readers never see a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=path.suffix)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
