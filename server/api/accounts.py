"""Operator accounts: argon2-hashed passwords, roles, and bearer tokens (hashed at rest)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timedelta
from typing import Any, TypeVar

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from server.errors import Conflict
from server.link.limits import TokenBucket
from server.link.robots import hash_token
from server.storage.models import AuthToken, Role, User, utcnow
from server.storage.space import is_disk_full

log = logging.getLogger(__name__)
# tokens handed out while the storage was full (the database could not take their rows):
# valid until they expire or the station stops
_unstored: dict[str, tuple[int, datetime]] = {}
_unstored_lock = threading.Lock()
ROLE_RANK = {Role.viewer: 0, Role.operator: 1, Role.admin: 2}
TOKEN_LIFETIME = timedelta(hours=12)
_hasher = PasswordHasher()


def create_user(factory: sessionmaker[Session], name: str, password: str, role: Role) -> None:
    """Add an account; raise ValueError for an empty name or a short password."""
    if not name.strip():
        raise ValueError("user name must not be empty")
    if len(password) < 8:
        raise ValueError("password must have at least 8 characters")
    with factory() as db:
        db.add(User(name=name.strip(), password_hash=_hasher.hash(password), role=role))
        try:
            db.commit()
        except IntegrityError:
            raise Conflict(f"a user named {name!r} already exists") from None


def set_password(db: Session, user: User, password: str) -> None:
    """Give an account a new password; its tokens stop working (sign in again)."""
    if len(password) < 8:
        raise ValueError("password must have at least 8 characters")
    user.password_hash = _hasher.hash(password)
    db.execute(delete(AuthToken).where(AuthToken.user_id == user.id))


def accounts_exist(db: Session) -> bool:
    """Whether any operator account exists (without one the station is open, as on a bench)."""
    return (db.scalar(select(func.count()).select_from(User)) or 0) > 0


def issue_token(
    factory: sessionmaker[Session], name: str, password: str
) -> tuple[str, User] | None:
    """A new bearer token for a correct name and password, else None."""
    with factory() as db:
        user = db.scalar(select(User).where(User.name == name))
        if user is None:
            _hasher.hash(password)  # spend the same time as a real check
            return None
        try:
            _hasher.verify(user.password_hash, password)
        except (VerificationError, InvalidHashError):
            return None
        token = secrets.token_urlsafe(32)
        now = utcnow()
        try:
            db.execute(delete(AuthToken).where(AuthToken.expires_at < now))
            db.add(
                AuthToken(
                    token_hash=hash_token(token), user_id=user.id, expires_at=now + TOKEN_LIFETIME
                )
            )
            db.commit()
        except (OperationalError, OSError) as exc:
            if not is_disk_full(exc):
                raise
            db.rollback()  # signed in all the same, to see the storage warning and act on it
            log.warning("storage full: %s's sign-in kept in memory until the station stops", name)
            with _unstored_lock:
                _unstored[hash_token(token)] = (user.id, now + TOKEN_LIFETIME)
        return token, user


def user_for_token(db: Session, token: str | None) -> User | None:
    """The account a bearer token belongs to, if the token is valid and unexpired."""
    if not token:
        return None
    digest = hash_token(token)
    row = db.get(AuthToken, digest)
    if row is None:
        with _unstored_lock:
            kept = _unstored.get(digest)
        if kept is None:
            return None
        user_id, expires = kept
    else:
        user_id, expires = row.user_id, row.expires_at
    if expires.tzinfo is None:
        expires = expires.replace(tzinfo=utcnow().tzinfo)
    if expires < utcnow():
        return None
    return db.get(User, user_id)


def revoke_token(db: Session, token: str | None) -> bool:
    """Make a bearer token invalid (signing out); whether it was valid."""
    if not token:
        return False
    with _unstored_lock:
        kept = _unstored.pop(hash_token(token), None)
    gone = db.execute(delete(AuthToken).where(AuthToken.token_hash == hash_token(token)))
    db.commit()
    return bool(gone.rowcount) or kept is not None


def has_role(user: User, role: Role) -> bool:
    """Whether the user's role is at least ``role``."""
    return ROLE_RANK[user.role] >= ROLE_RANK[role]


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
