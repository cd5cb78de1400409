"""Free space of the data directory, kept above a reserve: below it the station refuses new
robot data with "retry later" before SQLite or the filesystem fail half-way."""

from __future__ import annotations

import errno
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from server.errors import IngestError

MIB = 2**20
DISK_FULL_SQLSTATES = ("53100", "53200")  # PostgreSQL: disk full, out of memory


@dataclass(frozen=True)
class SpaceStatus:
    """What ``GET /api/health`` reports of the data directory's disk."""

    free_bytes: int
    reserve_bytes: int

    @property
    def accepting(self) -> bool:
        return self.free_bytes > self.reserve_bytes


class DiskReserve:
    """Watches the free bytes of the filesystem holding ``path``.

    ``statvfs`` is asked at most every ``interval_s``; between two asks the bytes the
    station has let through are subtracted, so a burst cannot run past the reserve."""

    def __init__(self, path: Path, reserve_bytes: int, interval_s: float = 0.5) -> None:
        self.path = path
        self.reserve_bytes = reserve_bytes
        self.interval_s = interval_s
        self._lock = threading.Lock()
        self._free = 0
        self._asked = -float("inf")

    def status(self) -> SpaceStatus:
        with self._lock:
            return SpaceStatus(self._free_now(), self.reserve_bytes)

    def claim(self, size: int, headroom: int = 0) -> None:
        """Let ``size`` bytes be stored, or raise a retryable IngestError if they would
        leave less than the reserve (and ``headroom`` beyond it) free."""
        with self._lock:
            free = self._free_now()
            if free - size < self.reserve_bytes + headroom:
                raise IngestError(
                    f"ground station storage is full ({free / MIB:.0f} MiB free, "
                    f"{(self.reserve_bytes + headroom) / MIB:.0f} MiB kept free): retry later",
                    retry=True,
                )
            self._free = free - size

    def _free_now(self) -> int:
        now = time.monotonic()
        if now - self._asked >= self.interval_s:
            try:
                self._free = shutil.disk_usage(self.path).free
            except OSError:
                self._free = 0  # the data directory is gone or unreadable: store nothing
            self._asked = now
        return self._free


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) says the filesystem or SQLite ran out of room:
    ``ENOSPC``/``EDQUOT``, SQLite's "database or disk is full" (SQLITE_FULL), PostgreSQL's
    disk-full class of errors."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, OSError) and cause.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if getattr(cause, "sqlstate", None) in DISK_FULL_SQLSTATES:  # PostgreSQL's
            return True
        if any(text in str(cause) for text in ("database or disk is full", "No space left")):
            return True
        cause = cause.__cause__ or cause.__context__
    return False
