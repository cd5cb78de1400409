"""Commands delivered again are never acted on twice: a command whose seq is not above the
last one acted on is a replay (stopping is always safe, whatever its seq)."""

from __future__ import annotations

import logging

from robot_link.protocol import STOP_COMMANDS, Message

log = logging.getLogger(__name__)


class CommandGate:
    """Admits each command once, in seq order; stop and e-stop always."""

    def __init__(self) -> None:
        self.last_seq = 0

    def admit(self, message: Message) -> bool:
        """Whether to act on this COMMAND."""
        cmd = message.meta.get("cmd")
        if message.seq <= self.last_seq and cmd not in STOP_COMMANDS:
            log.warning(
                "link: ignoring command %r with stale seq %d (last %d)",
                cmd,
                message.seq,
                self.last_seq,
            )
            return False
        self.last_seq = max(self.last_seq, message.seq)
        return True
