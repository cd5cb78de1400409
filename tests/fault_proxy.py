"""A fault-injecting TCP proxy on loopback: it forwards a client to a server and, at random,
cuts the connection, stalls it or delays it, to test that the link loses nothing."""

from __future__ import annotations

import asyncio
import random
from dataclasses import dataclass, field


@dataclass
class FaultProxy:
    """Forward ``listen`` → ``target`` with random cuts, stalls and delays (seeded)."""

    target_port: int
    seed: int = 0
    cut_probability: float = 0.02  # per forwarded chunk
    stall_probability: float = 0.02
    stall_s: tuple[float, float] = (0.2, 1.5)
    delay_s: tuple[float, float] = (0.0, 0.01)
    cuts: int = 0
    stalls: int = 0
    connections: int = 0
    _rng: random.Random = field(init=False)
    _server: asyncio.AbstractServer | None = field(default=None, init=False)
    # the cut switch of each open connection
    _open: set[asyncio.Event] = field(default_factory=set, init=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    async def start(self) -> int:
        """Listen on a free loopback port; returns it."""
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        return int(self._server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        """Stop listening."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    def cut_all(self) -> None:
        """Drop every open connection now, as a wireless link does (no close handshake)."""
        self.cuts += len(self._open)
        for cut in self._open:
            cut.set()

    async def _serve(self, client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            server_r, server_w = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            client_w.close()
            return
        cut = asyncio.Event()
        self._open.add(cut)
        waiter = asyncio.ensure_future(self._cut_on(cut, client_w, server_w))
        await asyncio.gather(
            self._pipe(client_r, server_w, cut),
            self._pipe(server_r, client_w, cut),
            return_exceptions=True,
        )
        self._open.discard(cut)
        waiter.cancel()
        for w in (client_w, server_w):
            w.transport.abort() if cut.is_set() else w.close()

    @staticmethod
    async def _cut_on(cut: asyncio.Event, *writers: asyncio.StreamWriter) -> None:
        """Abort both sides as soon as ``cut`` is set (a pipe may be waiting in a read)."""
        await cut.wait()
        for w in writers:
            w.transport.abort()

    async def _pipe(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, cut: asyncio.Event
    ) -> None:
        while not cut.is_set():
            chunk = await reader.read(65536)
            if not chunk:
                break
            roll = self._rng.random()
            if roll < self.cut_probability and self.connections < 50:
                self.cuts += 1
                cut.set()  # the wireless link drops: no close handshake
                break
            if roll < self.cut_probability + self.stall_probability:
                self.stalls += 1
                await asyncio.sleep(self._rng.uniform(*self.stall_s))
            else:
                await asyncio.sleep(self._rng.uniform(*self.delay_s))
            writer.write(chunk)
            await writer.drain()
        cut.set()
        writer.transport.abort()
