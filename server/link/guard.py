"""Limits on connections before anyone is authenticated: at most so many open connections
per client address and on the whole station, a deadline for each request head (the
request line and headers), and a station-wide bound on connections still sending their
head, the oldest of which gives way to a newcomer, so sockets that trickle a partial
request cannot hold the station's descriptors or keep a robot out. The station raises its
own descriptor limit at start (:func:`raise_fd_limit`)."""

from __future__ import annotations

import asyncio
import logging
import resource
from collections import OrderedDict, defaultdict

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from server.limits import TokenBucket

log = logging.getLogger(__name__)
NEW_PER_S, NEW_BURST = 100.0, 300.0  # new connections an address may open (a reconnect storm)
MAX_ADDRESSES = 10_000


FD_RESERVE = 256  # descriptors kept for files, the database and worker pipes
FD_WANTED = 65536  # the soft limit the station raises itself to (within the hard one)


def raise_fd_limit(wanted: int = FD_WANTED) -> int:
    """Raise this process's soft limit on open files towards ``wanted`` (at most its hard
    limit); the limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = wanted if hard == resource.RLIM_INFINITY else min(wanted, hard)
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:
            log.warning("could not raise the open-file limit from %d: %s", soft, exc)
    return soft


def connection_budget(max_connections: int) -> int:
    """Connections the station holds at most: ``max_connections``, or (0) what its
    descriptor limit leaves beside :data:`FD_RESERVE`."""
    if max_connections > 0:
        return max_connections
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return max(64, soft - FD_RESERVE)


def guarded_http(
    max_per_client: int,
    head_timeout_s: float,
    new_per_s: float = NEW_PER_S,
    new_burst: float = NEW_BURST,
    *,
    max_connections: int = 0,
    max_pending: int = 256,
) -> type[HttpToolsProtocol]:
    """uvicorn's HTTP protocol (``uvicorn.Config(http=...)``) with the limits; one class per
    server, counting that server's connections (websockets included: an upgraded connection
    keeps its transport). New connections from one address beyond ``new_per_s`` a second
    (``new_burst`` at once) are closed as they arrive, before a byte is parsed. At most
    ``max_pending`` connections may be sending a request head at once, station-wide: a new
    one closes the one that has been at it longest (a real client sends its head in
    milliseconds). At most ``max_connections`` (:func:`connection_budget`) are open in all;
    beyond, a new one takes the place of the oldest pending one, or is closed."""
    open_by_client: dict[str, set[asyncio.BaseTransport]] = defaultdict(set)
    arrivals: dict[str, TokenBucket] = {}
    pending: OrderedDict[HttpToolsProtocol, None] = OrderedDict()  # sending a head, oldest first
    every: set[asyncio.BaseTransport] = set()  # an upgraded websocket keeps its transport

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
            budget = connection_budget(max_connections)
            if len(every) >= budget:
                every.difference_update([t for t in every if t.is_closing()])
            if len(every) >= budget or len(pending) >= max_pending:
                if not pending:
                    log.warning("refused a connection: %d open, the station's limit", len(every))
                    transport.close()
                    return
                oldest = next(iter(pending))
                oldest._forget()
                oldest.transport.close()
            mine.add(transport)
            every.add(transport)
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
            self._forget()
            super().connection_lost(exc)
            if self.client is not None:
                mine = open_by_client.get(self.client[0])
                if mine is not None:
                    mine.discard(self.transport)
                    if not mine:
                        del open_by_client[self.client[0]]

        def _arm(self) -> None:
            self._head_timer = self.loop.call_later(head_timeout_s, self._head_late)
            pending[self] = None

        def _disarm(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None
            pending.pop(self, None)

        def _forget(self) -> None:
            pending.pop(self, None)
            every.discard(self.transport)

        def _head_late(self) -> None:
            self._head_timer = None
            pending.pop(self, None)
            if not self.transport.is_closing():
                self.transport.close()

    return GuardedHttp
