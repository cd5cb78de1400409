"""The robot's durable spool: every message not yet acknowledged by the ground station, on disk.

One file per message (``<seq>.msg``), written atomically (temporary name, fsync, rename)
before the message is first sent and deleted when its ACK arrives; ``session.json`` keeps
the session id and the next sequence number, so a robot whose computer restarted resumes
the same session and resends what was never acknowledged. The spool has a size bound:
``put`` refuses a message that would pass it (the caller waits for ACKs to make room), and
``near_full`` says when it is close.
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path


class SpoolFull(RuntimeError):
    """The spool has no room for another message until some are acknowledged."""


class Spool:
    """Unacknowledged messages of one robot session, on disk, bounded in bytes."""

    def __init__(
        self,
        directory: Path,
        *,
        max_bytes: int = 2 * 2**30,
        warn_fraction: float = 0.8,
        fsync: bool = True,
    ) -> None:
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self.warn_fraction = warn_fraction
        self.fsync = fsync
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.glob("*.tmp"):  # a write cut short by a crash never happened
            stale.unlink(missing_ok=True)
        self._sizes = {
            int(p.stem): p.stat().st_size for p in self.directory.glob("*.msg") if p.stem.isdigit()
        }

    @property
    def used_bytes(self) -> int:
        """Bytes held by spooled messages."""
        return sum(self._sizes.values())

    @property
    def near_full(self) -> bool:
        """Whether the spool holds more than ``warn_fraction`` of its bound."""
        return self.used_bytes >= self.warn_fraction * self.max_bytes

    def __len__(self) -> int:
        return len(self._sizes)

    def _path(self, seq: int) -> Path:
        return self.directory / f"{seq:012d}.msg"

    def _write(self, path: Path, data: bytes) -> None:
        tmp = path.with_name(path.name + ".tmp")
        with tmp.open("wb") as f:
            f.write(data)
            if self.fsync:
                f.flush()
                os.fsync(f.fileno())
        tmp.replace(path)

    def room_for(self, size: int) -> bool:
        """Whether a message of ``size`` bytes fits under the bound."""
        return self.used_bytes + size <= self.max_bytes or not self._sizes

    def put(self, seq: int, data: bytes) -> None:
        """Keep a message until :meth:`remove`; :class:`SpoolFull` past the bound."""
        if not self.room_for(len(data)):
            raise SpoolFull(
                f"spool full: {self.used_bytes} of {self.max_bytes} bytes held by {len(self)} unacknowledged messages"
            )
        self._write(self._path(seq), data)
        self._sizes[seq] = len(data)

    def remove(self, seq: int) -> None:
        """Forget an acknowledged message."""
        if self._sizes.pop(seq, None) is not None:
            self._path(seq).unlink(missing_ok=True)

    def read(self, seq: int) -> bytes:
        """A spooled message's bytes."""
        return self._path(seq).read_bytes()

    def pending(self) -> list[int]:
        """Sequence numbers of the spooled messages, in order."""
        return sorted(self._sizes)

    def load_session(self) -> tuple[uuid.UUID, int] | None:
        """The session id and next sequence number saved by :meth:`save_session`, if any."""
        path = self.directory / "session.json"
        if not path.is_file():
            return None
        doc = json.loads(path.read_text())
        return uuid.UUID(doc["session_id"]), int(doc["next_seq"])

    def save_session(self, session_id: uuid.UUID, next_seq: int) -> None:
        """Remember the session and a sequence number not used yet (atomically). The link
        saves a block ahead, so a restart never reuses a number (a reused one would read as a
        resend and be dropped as a duplicate); gaps are fine."""
        self._write(
            self.directory / "session.json",
            json.dumps({"session_id": str(session_id), "next_seq": next_seq}).encode(),
        )
