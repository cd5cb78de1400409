"""Operator accounts: argon2-hashed passwords, roles, and bearer tokens (hashed at rest)."""

from __future__ import annotations

import logging
import secrets
import threading
from datetime import datetime, timedelta

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from server.errors import Conflict
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
