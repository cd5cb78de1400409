"""Robot registration and token checks (tokens are stored only as SHA-256 hashes)."""

from __future__ import annotations

import hashlib
import hmac
import secrets

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from server.errors import Conflict
from server.storage.models import Robot
from server.tokens import TOKEN_PREFIX


def hash_token(token: str) -> str:
    """Hex SHA-256 of a token."""
    return hashlib.sha256(token.encode()).hexdigest()


def create_robot(factory: sessionmaker[Session], name: str) -> str:
    """Register a robot and return its new token (shown once, never stored in clear)."""
    if not name.strip():
        raise ValueError("robot name must not be empty")
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with factory() as db:
        db.add(Robot(name=name.strip(), token_hash=hash_token(token)))
        try:
            db.commit()
        except IntegrityError:
            raise Conflict(f"a robot named {name!r} already exists") from None
    return token


def authenticate_robot(factory: sessionmaker[Session], token: str | None) -> Robot | None:
    """The robot a token belongs to, or None."""
    if not token:
        return None
    digest = hash_token(token)
    with factory() as db:
        robot = db.scalar(select(Robot).where(Robot.token_hash == digest))
    if robot is None or not hmac.compare_digest(robot.token_hash, digest):
        return None
    return robot
