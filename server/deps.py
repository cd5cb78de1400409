"""Shared route dependencies as Annotated aliases."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from server.state import AppState


def get_state(request: Request) -> AppState:
    """The app's shared state."""
    return request.app.state.steelscan


def get_db(request: Request) -> Iterator[Session]:
    """A database session for one request."""
    with request.app.state.steelscan.factory() as db:
        yield db


StateDep = Annotated[AppState, Depends(get_state)]
SessionDep = Annotated[Session, Depends(get_db)]
