"""Rate limits on connections: a token bucket per robot and per browser."""

from __future__ import annotations

import time


class TokenBucket:
    """At most ``rate`` events a second on average, ``burst`` at once."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.t = time.monotonic()

    def take(self) -> bool:
        """Spend a token if there is one."""
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now
        if self.tokens < 1:
            return False
        self.tokens -= 1
        return True


class MalformedGuard:
    """Per robot (across its reconnections): malformed messages allowed at ``rate`` a second
    (``burst`` at once); a robot over it is barred for ``bar_s``, doubled for each bar in a
    row up to ``max_bar_s``. A compliant robot never sends a malformed message."""

    def __init__(
        self, rate: float = 20.0, burst: float = 100.0, bar_s: float = 5.0, max_bar_s: float = 300.0
    ) -> None:
        self.rate, self.burst, self.bar_s, self.max_bar_s = rate, burst, bar_s, max_bar_s
        self._buckets: dict[int, TokenBucket] = {}
        self._barred: dict[int, tuple[float, float]] = {}  # robot -> (until, last bar length)
        self._tokens: dict[str, int] = {}  # token digest -> barred robot: refused unheard

    def barred_for(self, robot_id: int) -> float:
        """Seconds the robot must still wait before it may connect (0: now)."""
        until, _ = self._barred.get(robot_id, (0.0, 0.0))
        return max(0.0, until - time.monotonic())

    def token_barred(self, digest: str) -> bool:
        """Whether a token (its digest) belongs to a robot barred now: refused before the
        database is asked."""
        robot = self._tokens.get(digest)
        return robot is not None and self.barred_for(robot) > 0

    def malformed(self, robot_id: int, digest: str) -> bool:
        """Count one malformed message from a robot connected with the token of ``digest``;
        False when the robot is now barred."""
        bucket = self._buckets.setdefault(robot_id, TokenBucket(self.rate, self.burst))
        if bucket.take():
            return True
        now = time.monotonic()
        until, last = self._barred.get(robot_id, (0.0, 0.0))
        length = min(self.max_bar_s, 2 * last) if now - until < self.max_bar_s else self.bar_s
        self._barred[robot_id] = (now + max(length, self.bar_s), max(length, self.bar_s))
        self._tokens[digest] = robot_id
        return False
