"""Rate limits: a token bucket per robot and per browser connection, a bar on robots that
send malformed messages, and the sign-in's throttle and password-checking budget."""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar


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


T = TypeVar("T")
PASSWORD_NICE = 10  # the password thread's priority below the station's (Linux: per thread)


def _lower_priority() -> None:
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), PASSWORD_NICE)


ANY_USER = "\x00any"  # the key of a client's failures over every user name


class LoginThrottle:
    """Refuses logins for a (client, user name) after ``max_failures`` wrong passwords within
    ``window_s``, and for a client after ``max_client_failures`` over every user name (so
    guessing across many names is throttled too), until the oldest of them is that old.
    Bounded: at most ``max_keys`` keys are remembered."""

    def __init__(
        self,
        max_failures: int = 5,
        window_s: float = 60.0,
        max_keys: int = 10_000,
        max_client_failures: int = 20,
    ) -> None:
        self.max_failures = max_failures
        self.max_client_failures = max_client_failures
        self.window_s = window_s
        self.max_keys = max_keys
        self._failures: dict[tuple[str, str], deque[float]] = {}
        self._lock = threading.Lock()

    def retry_after(self, client: str, name: str) -> float:
        """Seconds until this pair may try again (0: now)."""
        now = time.monotonic()
        with self._lock:
            return max(
                self._wait((client, name), self.max_failures, now),
                self._wait((client, ANY_USER), self.max_client_failures, now),
            )

    def _wait(self, key: tuple[str, str], limit: int, now: float) -> float:
        times = self._failures.get(key)
        if times is None:
            return 0.0
        while times and now - times[0] > self.window_s:
            times.popleft()
        if len(times) < limit:
            return 0.0
        return self.window_s - (now - times[0])

    def failed(self, client: str, name: str) -> None:
        """Count a wrong password."""
        now = time.monotonic()
        with self._lock:
            if len(self._failures) >= self.max_keys - 1:
                # forget the keys whose failures are all old, then the oldest keys
                self._failures = {
                    k: v for k, v in self._failures.items() if v and now - v[-1] <= self.window_s
                }
                for key in list(self._failures)[: max(0, len(self._failures) - self.max_keys + 2)]:
                    del self._failures[key]
            self._failures.setdefault((client, name), deque(maxlen=self.max_failures)).append(now)
            self._failures.setdefault(
                (client, ANY_USER), deque(maxlen=self.max_client_failures)
            ).append(now)

    def succeeded(self, client: str, name: str) -> None:
        """Forget this pair's failures (the client's count over all names stays)."""
        with self._lock:
            self._failures.pop((client, name), None)


class PasswordBudget:
    """Password hashing (argon2: ~0.1 s of several cores each) for the whole station: at
    most ``rate`` checks a second (``burst`` at once), one at a time on one thread of low
    scheduling priority (its argon2 lanes inherit it), so logins can never take the CPU
    the robots' ingest needs.

    Each client address has a share of its own first (``client_rate``, ``client_burst``,
    half the station's burst): one address flooding the sign-in spends its share, never
    the whole budget, so an operator elsewhere still signs in; a right password gives its
    check back (:meth:`refund`). At most ``max_clients`` addresses are remembered."""

    def __init__(
        self,
        rate: float = 1.0,
        burst: float = 12.0,
        client_rate: float = 0.25,
        client_burst: float = 6.0,
        max_clients: int = 10_000,
    ) -> None:
        self._bucket = TokenBucket(rate, burst)
        self.client_rate, self.client_burst, self.max_clients = (
            client_rate,
            client_burst,
            max_clients,
        )
        self._clients: dict[str, TokenBucket] = {}
        self._lock = threading.Lock()
        self.executor = ThreadPoolExecutor(
            1, thread_name_prefix="passwords", initializer=_lower_priority
        )

    def take_for(self, client: str) -> bool:
        """Whether a check for ``client`` (its address) may start now: within its own share,
        then within the station's budget."""
        with self._lock:
            bucket = self._clients.pop(client, None)  # re-inserted: most recent last
            if bucket is None:
                bucket = TokenBucket(self.client_rate, self.client_burst)
                while len(self._clients) >= self.max_clients:  # forget the longest idle
                    del self._clients[next(iter(self._clients))]
            self._clients[client] = bucket
            if not bucket.take():
                return False
            if not self._bucket.take():
                bucket.tokens += 1  # not spent: the station's budget refused it
                return False
            return True

    def refund(self, client: str) -> None:
        """Give ``client`` back the check it spent on a right password: its share counts
        wrong passwords, so an operator who signs in often never runs out."""
        with self._lock:
            bucket = self._clients.get(client)
            if bucket is not None:
                bucket.tokens = min(bucket.burst, bucket.tokens + 1)

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on the password thread."""
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)
