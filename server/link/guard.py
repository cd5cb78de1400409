"""Limits on connections before anyone is authenticated: at most so many open connections
per client address, and a deadline for each request head (the request line and headers),
so sockets that trickle a partial request cannot hold the station's descriptors."""

from __future__ import annotations

import asyncio
import logging
from collections import defaultdict

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from server.link.limits import TokenBucket

log = logging.getLogger(__name__)
NEW_PER_S, NEW_BURST = 100.0, 300.0  # new connections an address may open (a reconnect storm)
MAX_ADDRESSES = 10_000


def guarded_http(
    max_per_client: int,
    head_timeout_s: float,
    new_per_s: float = NEW_PER_S,
    new_burst: float = NEW_BURST,
) -> type[HttpToolsProtocol]:
    """uvicorn's HTTP protocol (``uvicorn.Config(http=...)``) with the limits; one class per
    server, counting that server's connections (websockets included: an upgraded connection
    keeps its transport). New connections from one address beyond ``new_per_s`` a second
    (``new_burst`` at once) are closed as they arrive, before a byte is parsed."""
    open_by_client: dict[str, set[asyncio.BaseTransport]] = defaultdict(set)
    arrivals: dict[str, TokenBucket] = {}

    class GuardedHttp(HttpToolsProtocol):
        _head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            host = self.client[0] if self.client else "?"
            if len(arrivals) > MAX_ADDRESSES:
                arrivals.clear()  # a flood of spoofed addresses: start counting afresh
            if not arrivals.setdefault(host, TokenBucket(new_per_s, new_burst)).take():
                transport.close()
                return
            mine = open_by_client[host]
            mine.difference_update([t for t in mine if t.is_closing()])
            if len(mine) >= max_per_client:
                log.warning("refused a connection: %s has %d open", host, len(mine))
                transport.close()
                return
            mine.add(transport)
            self._arm()

        def on_message_begin(self) -> None:
            super().on_message_begin()
            if self._head_timer is None:  # the next request on a kept-alive connection
                self._arm()

        def on_headers_complete(self) -> None:
            self._disarm()
            super().on_headers_complete()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)
            if self.client is not None:
                mine = open_by_client.get(self.client[0])
                if mine is not None:
                    mine.discard(self.transport)
                    if not mine:
                        del open_by_client[self.client[0]]

        def _arm(self) -> None:
            self._head_timer = self.loop.call_later(head_timeout_s, self._head_late)

        def _disarm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_late(self) -> None:
            self._head_timer = None
            if not self.transport.is_closing():
                self.transport.close()

    return GuardedHttp
