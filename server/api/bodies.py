"""Request bodies under control (pure ASGI middleware): a request that carries a body is
authenticated before a byte of it is read, refused at once when it says it is larger than
its route allows, stopped when it grows past that, and must arrive within a deadline, so
that nobody on the network can fill the disk or hold connections open with a slow body."""

from __future__ import annotations

import json
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import anyio
from starlette.types import ASGIApp, Message, Receive, Scope, Send

Authenticate = Callable[[Scope, str | None], Awaitable[bool]]


@dataclass(frozen=True)
class BodyLimits:
    """How large a body may be, and how fast it must come.

    ``max_bytes``: any route's cap; ``large``: routes (path → cap) that take more (an
    import). A body must have arrived ``grace_s`` plus its size at ``min_rate_bps`` after the
    request began, with no gap between two of its chunks longer than ``idle_s``."""

    max_bytes: int = 1 << 20
    large: tuple[tuple[str, int], ...] = ()
    grace_s: float = 20.0
    min_rate_bps: float = 64 * 1024
    idle_s: float = 15.0

    def cap(self, path: str) -> int:
        return dict(self.large).get(path, self.max_bytes)


class RequestBodies:
    """See the module's docstring. ``authenticate(scope, bearer_token)`` says whether the
    caller may send a body; paths in ``open_paths`` (signing in) need no token."""

    def __init__(
        self,
        app: ASGIApp,
        limits: BodyLimits,
        authenticate: Authenticate,
        open_paths: frozenset[str] = frozenset(),
    ) -> None:
        self.app, self.limits = app, limits
        self.authenticate, self.open_paths = authenticate, open_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not _has_body(scope):
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        cap = self.limits.cap(path)
        declared = _content_length(scope)
        if declared is not None and declared > cap:
            await _refuse(send, 413, f"the request body is larger than {cap} bytes")
            return
        if path not in self.open_paths and not await self.authenticate(scope, _bearer(scope)):
            await _refuse(send, 401, "a valid bearer token is required", bearer=True)
            return
        began = time.monotonic()
        received = 0
        answered = False  # by this middleware: the app's own answer is dropped
        started = False

        async def answer(status: int, detail: str) -> Message:
            nonlocal answered
            if not started and not answered:
                await _refuse(send, status, detail)
            answered = True
            return {"type": "http.disconnect"}  # to the app: the client has gone

        async def timed_receive() -> Message:
            nonlocal received
            if answered:
                return {"type": "http.disconnect"}
            # a body of known size has its time from the start; one of unknown size earns
            # time as it arrives
            size = declared if declared is not None else received
            deadline = began + self.limits.grace_s + size / self.limits.min_rate_bps
            wait = min(self.limits.idle_s, deadline - time.monotonic())
            message: Message | None = None
            if wait > 0:
                with anyio.move_on_after(wait):
                    message = await receive()
            if message is None:
                return await answer(408, "the request body did not arrive in time")
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > cap:
                    return await answer(413, f"the request body is larger than {cap} bytes")
            return message

        async def watched_send(message: Message) -> None:
            nonlocal started
            if answered:
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, timed_receive, watched_send)
        except Exception:
            if not answered:
                raise


def _has_body(scope: Scope) -> bool:
    headers = dict(scope.get("headers", []))
    length = headers.get(b"content-length")
    if length is not None:
        return length.strip() not in (b"0", b"")
    return b"transfer-encoding" in headers or scope["method"] in ("POST", "PUT", "PATCH")


def _content_length(scope: Scope) -> int | None:
    for key, value in scope.get("headers", []):
        if key == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


def _bearer(scope: Scope) -> str | None:
    for key, value in scope.get("headers", []):
        if key == b"authorization":
            text = value.decode("latin-1")
            if text.lower().startswith("bearer "):
                return text[7:].strip()
    return None


async def _refuse(send: Send, status: int, detail: str, *, bearer: bool = False) -> None:
    """Answer with a JSON error and close the connection (the body is left unread)."""
    headers = [(b"content-type", b"application/json"), (b"connection", b"close")]
    if bearer:
        headers.append((b"www-authenticate", b"Bearer"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": json.dumps({"detail": detail}).encode()})
