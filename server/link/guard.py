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
from dataclasses import dataclass, field

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


@dataclass
class ConnectionLimits:
    """One server's limits and the connections it counts (websockets included: an upgraded
    connection keeps its transport)."""

    max_per_client: int
    head_timeout_s: float
    new_per_s: float = NEW_PER_S
    new_burst: float = NEW_BURST
    max_connections: int = 0
    max_pending: int = 256
    open_by_client: dict[str, set[asyncio.BaseTransport]] = field(
        default_factory=lambda: defaultdict(set)
    )
    arrivals: dict[str, TokenBucket] = field(default_factory=dict)
    # connections sending a request head, oldest first
    pending: OrderedDict[GuardedHttp, None] = field(default_factory=OrderedDict)
    every: set[asyncio.BaseTransport] = field(default_factory=set)

    def admit(self, transport: asyncio.Transport, host: str) -> bool:
        """Whether a new connection from ``host`` may stay: within the address's arrival
        rate and open connections, and the station's; a full station lets the
        longest-pending connection go for it."""
        if len(self.arrivals) > MAX_ADDRESSES:
            self.arrivals.clear()  # a flood of spoofed addresses: start counting afresh
        if not self.arrivals.setdefault(host, TokenBucket(self.new_per_s, self.new_burst)).take():
            return False
        mine = self.open_by_client[host]
        mine.difference_update([t for t in mine if t.is_closing()])
        if len(mine) >= self.max_per_client:
            log.warning("refused a connection: %s has %d open", host, len(mine))
            return False
        budget = connection_budget(self.max_connections)
        if len(self.every) >= budget:
            self.every.difference_update([t for t in self.every if t.is_closing()])
        if len(self.every) >= budget or len(self.pending) >= self.max_pending:
            if not self.pending:
                log.warning("refused a connection: %d open, the station's limit", len(self.every))
                return False
            oldest = next(iter(self.pending))
            oldest.forget()
            oldest.transport.close()
        mine.add(transport)
        self.every.add(transport)
        return True

    def lost(self, transport: asyncio.BaseTransport, host: str | None) -> None:
        """A connection closed."""
        self.every.discard(transport)
        mine = self.open_by_client.get(host) if host is not None else None
        if host is not None and mine is not None:
            mine.discard(transport)
            if not mine:
                del self.open_by_client[host]


class GuardedHttp(HttpToolsProtocol):
    """uvicorn's HTTP protocol under its server's :class:`ConnectionLimits`, with a
    deadline for each request head."""

    limits: ConnectionLimits
    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self.limits.admit(transport, self.client[0] if self.client else "?"):
            transport.close()
            return
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
        self.forget()
        super().connection_lost(exc)
        self.limits.lost(self.transport, self.client[0] if self.client else None)

    def forget(self) -> None:
        """No longer counted as pending, nor as open."""
        self.limits.pending.pop(self, None)
        self.limits.every.discard(self.transport)

    def _arm(self) -> None:
        self._head_timer = self.loop.call_later(self.limits.head_timeout_s, self._head_late)
        self.limits.pending[self] = None

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None
        self.limits.pending.pop(self, None)

    def _head_late(self) -> None:
        self._head_timer = None
        self.limits.pending.pop(self, None)
        if not self.transport.is_closing():
            self.transport.close()


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
    server, counting that server's connections. New connections from one address beyond
    ``new_per_s`` a second (``new_burst`` at once) are closed as they arrive, before a byte
    is parsed. At most ``max_pending`` connections may be sending a request head at once,
    station-wide: a new one closes the one that has been at it longest (a real client sends
    its head in milliseconds). At most ``max_connections`` (:func:`connection_budget`) are
    open in all; beyond, a new one takes the place of the oldest pending one, or is closed."""
    limits = ConnectionLimits(
        max_per_client, head_timeout_s, new_per_s, new_burst, max_connections, max_pending
    )
    return type("GuardedHttp", (GuardedHttp,), {"limits": limits})
