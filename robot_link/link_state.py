"""What the link client knows of its link: its failure that resending cannot fix, its
counters, the station's robot endpoint and the message size limit the station states."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

from robot_link.protocol import MAX_BYTES_HEADER, MAX_MESSAGE_BYTES

log = logging.getLogger(__name__)


class LinkError(RuntimeError):
    """The link to the ground station failed in a way resending cannot fix."""


@dataclass
class LinkStats:
    """Counters the client keeps about its link."""

    sent: int = 0
    resent: int = 0
    acked: int = 0
    duplicates: int = 0
    reconnects: int = 0
    errors: int = 0
    last_ack_latency_s: float = 0.0
    spool_bytes: int = 0
    video_dropped: int = 0


def robot_ws_url(server_url: str) -> str:
    """Websocket address of the robot endpoint from the ground station's base URL."""
    base = server_url.rstrip("/")
    if base.startswith("https://"):
        base = "wss://" + base[len("https://") :]
    elif base.startswith("http://"):
        base = "ws://" + base[len("http://") :]
    elif not base.startswith(("ws://", "wss://")):
        raise ValueError(f"server_url must start with http:// or https://, got {server_url!r}")
    return base + "/ws/robot"


def stated_limit(headers: Mapping[str, str]) -> int | None:
    """The largest message the station takes, from its handshake's answer (the protocol's
    limit when it states none); None when what it states is not a number."""
    value = headers.get(MAX_BYTES_HEADER)
    if value is None:
        return MAX_MESSAGE_BYTES
    try:
        return int(value)
    except ValueError:
        log.warning("link: the station's %s is not a number: %r", MAX_BYTES_HEADER, value)
        return None
