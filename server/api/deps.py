"""Shared route dependencies as Annotated aliases."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Annotated
from urllib.parse import urlsplit

from fastapi import Depends, HTTPException, Request, WebSocket, status
from fastapi.security import OAuth2PasswordBearer
from sqlalchemy.orm import Session

from server.api.accounts import accounts_exist, has_role, user_for_token
from server.state import AppState
from server.storage.models import Role, User

oauth2 = OAuth2PasswordBearer(tokenUrl="/api/auth/token", auto_error=False)
ANONYMOUS = User(id=0, name="anonymous", password_hash="", role=Role.admin)


def get_state(request: Request) -> AppState:
    """The app's shared state."""
    return request.app.state.steelscan


def get_db(request: Request) -> Iterator[Session]:
    """A database session for one request."""
    with request.app.state.steelscan.factory() as db:
        yield db


def same_origin(websocket: WebSocket, allowed: list[str]) -> bool:
    """Whether a browser websocket comes from the station's own pages (its Origin names the
    host it connected to) or an ``allowed`` origin; clients that send no Origin (robots,
    scripts) are not browsers and pass. Refusing the rest stops another site's page, open
    in the operator's browser, from driving the robot (cross-site websocket hijacking)."""
    origin = websocket.headers.get("origin")
    if origin is None:
        return True
    if origin.rstrip("/") in {a.rstrip("/") for a in allowed}:
        return True
    return urlsplit(origin).netloc.lower() == websocket.headers.get("host", "").lower()


StateDep = Annotated[AppState, Depends(get_state)]
SessionDep = Annotated[Session, Depends(get_db)]


def get_current_user(db: SessionDep, token: Annotated[str | None, Depends(oauth2)]) -> User:
    """The caller; 401 without a valid token once accounts exist (open until the first one)."""
    if not accounts_exist(db):
        return ANONYMOUS
    user = user_for_token(db, token)
    if user is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "a valid bearer token is required",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return user


CurrentUser = Annotated[User, Depends(get_current_user)]


def require(role: Role) -> Callable[[User], User]:
    """Dependency: the caller must have at least ``role`` (403 otherwise)."""

    def check(user: CurrentUser) -> User:
        if not has_role(user, role):
            raise HTTPException(
                status.HTTP_403_FORBIDDEN,
                f"this needs the {role.value} role; you are {user.role.value}",
            )
        return user

    return check


OperatorUser = Annotated[User, Depends(require(Role.operator))]
AdminUser = Annotated[User, Depends(require(Role.admin))]
