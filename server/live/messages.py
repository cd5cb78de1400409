"""Messages a browser sends on ``/ws/live``, validated as one discriminated union.

``{"type": "control", "session_id", "action": "take" | "release", "force"}`` takes or
releases driving a robot; ``{"type": "command", "session_id", "cmd", "args"}`` (``type``
may be left out) commands it.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from robot_link.protocol import STOP_COMMANDS


class ControlMessage(BaseModel):
    """Take or release the driving of a session's robot."""

    model_config = ConfigDict(extra="ignore")
    type: Literal["control"]
    session_id: str
    action: Literal["take", "release"]
    force: bool = False


class CommandMessage(BaseModel):
    """A command for a session's robot (``drive``, ``stop``, ``estop``, ...)."""

    model_config = ConfigDict(extra="ignore")
    type: Literal["command"] = "command"
    session_id: str
    cmd: str
    args: dict[str, Any] = Field(default_factory=dict)


BrowserMessage = Annotated[ControlMessage | CommandMessage, Field(discriminator="type")]
_ADAPTER: TypeAdapter[ControlMessage | CommandMessage] = TypeAdapter(BrowserMessage)


class BadBrowserMessage(ValueError):
    """A browser message that is not JSON or not one of :data:`BrowserMessage`."""


def parse_browser_message(text: str) -> ControlMessage | CommandMessage:
    """The message in ``text``; raises :class:`BadBrowserMessage` saying what is wrong."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise BadBrowserMessage(f"not JSON: {exc}") from exc
    if not isinstance(raw, dict):
        raise BadBrowserMessage("a message must be a JSON object")
    raw.setdefault("type", "command")
    if raw.get("args") is None:
        raw.pop("args", None)
    for key in ("session_id", "cmd"):  # ids and command names may arrive as numbers
        if key in raw and not isinstance(raw[key], (str, dict, list)):
            raw[key] = str(raw[key])
    try:
        return _ADAPTER.validate_python(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"][1:]) or "message"
        raise BadBrowserMessage(f"{where}: {first['msg']}") from exc


def is_stop(text: str) -> bool:
    """Whether a browser message is a stop or e-stop command (never rate-limited)."""
    try:
        request = json.loads(text)
    except json.JSONDecodeError:
        return False
    return isinstance(request, dict) and request.get("cmd") in STOP_COMMANDS
