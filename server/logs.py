"""Logging without secrets: tokens in URLs (the browser's websockets and the 3D view carry
``?token=``), bearer headers and robot tokens are masked before any handler writes them."""

from __future__ import annotations

import copy
import logging
import re
from typing import Any

from server.tokens import TOKEN_PREFIX

MASK = "***"


# a secret: a token or password in a query string, a bearer credential, a robot token
_SECRETS = re.compile(
    r"(?P<query>(?<![\w-])(?:token|access_token|password)=)[^&\s\"']+"
    r"|(?P<bearer>Bearer\s+)[A-Za-z0-9._~+/=-]+"
    rf"|(?P<robot>{re.escape(TOKEN_PREFIX)})[A-Za-z0-9_-]+",
    re.IGNORECASE,
)


def redact(text: str) -> str:
    """``text`` with every token, password or bearer credential replaced by :data:`MASK`."""
    return _SECRETS.sub(
        lambda m: (m.group("query") or m.group("bearer") or m.group("robot")) + MASK, text
    )


class RedactSecrets(logging.Filter):
    """A handler filter that masks the secrets of each record's message (the record is
    always kept)."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Mask in the arguments where that suffices (uvicorn's access formatter reads
        them), else in the formatted message."""
        message = record.getMessage()
        clean = redact(message)
        if clean == message:
            return True
        if isinstance(record.args, tuple):
            args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
            if str(record.msg) % args == clean:
                record.args = args
                return True
        record.msg, record.args = clean, ()
        return True


def uvicorn_log_config() -> dict[str, Any]:
    """uvicorn's own logging configuration with :class:`RedactSecrets` on its handlers
    (its access log prints each request's query string)."""
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config.setdefault("filters", {})["redact"] = {"()": RedactSecrets}
    for handler in config["handlers"].values():
        handler.setdefault("filters", []).append("redact")
    return config
