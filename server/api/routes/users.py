"""User accounts (admin role): list, add, change role or password, remove."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, status
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import delete, func, select

from server.api.accounts import create_user, set_password
from server.api.deps import AdminUser, SessionDep, StateDep, require
from server.api.schemas import Text
from server.errors import Conflict, NotFound
from server.storage.models import AuthToken, Role, User, UserPreferences

router = APIRouter(prefix="/api/users", tags=["users"], dependencies=[Depends(require(Role.admin))])
Name = Annotated[Text, Field(min_length=1, max_length=200)]


class UserRow(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    name: str
    role: Role
    created_at: datetime


class UserCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Name
    password: str = Field(min_length=8, max_length=1000)
    role: Role = Role.viewer


class UserUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    role: Role | None = None
    password: str | None = Field(default=None, min_length=8, max_length=1000)


def _user_or_404(db: SessionDep, name: str) -> User:
    user = db.scalar(select(User).where(User.name == name))
    if user is None:
        raise NotFound(f"no user named {name!r}")
    return user


def _keep_an_admin(db: SessionDep, user: User) -> None:
    """Refuse a change that would leave the station without an admin."""
    admins = db.scalar(select(func.count()).select_from(User).where(User.role == Role.admin))
    if user.role == Role.admin and (admins or 0) <= 1:
        raise Conflict("the station needs at least one admin: make another admin first")


@router.get("", response_model=list[UserRow])
def read_users(db: SessionDep) -> list[User]:
    """Every account, by name."""
    return list(db.scalars(select(User).order_by(User.name)))


@router.post("", response_model=UserRow, status_code=status.HTTP_201_CREATED)
def add_user(db: SessionDep, state: StateDep, body: UserCreate) -> User:
    """Add an account (the first one switches sign-in on for everybody)."""
    try:
        create_user(state.factory, body.name, body.password, body.role)
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, str(exc)) from None
    return _user_or_404(db, body.name.strip())


@router.patch("/{name}", response_model=UserRow)
def update_user(db: SessionDep, name: str, body: UserUpdate) -> User:
    """Change an account's role or password (a new password signs it out everywhere)."""
    user = _user_or_404(db, name)
    if body.role is not None and body.role != user.role:
        _keep_an_admin(db, user)
        user.role = body.role
    if body.password is not None:
        set_password(db, user, body.password)
    db.commit()
    return user


@router.delete("/{name}", status_code=status.HTTP_204_NO_CONTENT)
def remove_user(db: SessionDep, name: str, caller: AdminUser) -> None:
    """Remove an account, its tokens and its preferences (not your own, not the last
    admin)."""
    user = _user_or_404(db, name)
    if user.name == caller.name:
        raise Conflict("you cannot remove your own account")
    _keep_an_admin(db, user)
    db.execute(delete(AuthToken).where(AuthToken.user_id == user.id))
    db.execute(delete(UserPreferences).where(UserPreferences.user_name == user.name))
    db.delete(user)
    db.commit()
