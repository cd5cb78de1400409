"""Tokens for REST clients (OAuth2 password flow) and who the caller is."""

from __future__ import annotations

from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, HTTPException, status
from fastapi.security import OAuth2PasswordRequestForm
from pydantic import BaseModel

from server.accounts import issue_token
from server.deps import CurrentUser, StateDep

router = APIRouter(prefix="/api/auth", tags=["auth"])


class TokenPublic(BaseModel):
    access_token: str
    token_type: str = "bearer"
    role: str


class UserPublic(BaseModel):
    name: str
    role: str


@router.post("/token", response_model=TokenPublic)
async def create_token(state: StateDep, form: Annotated[OAuth2PasswordRequestForm, Depends()]) -> TokenPublic:
    """Exchange a user name and password for a bearer token."""
    issued = await anyio.to_thread.run_sync(issue_token, state.factory, form.username, form.password)
    if issued is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong user name or password", headers={"WWW-Authenticate": "Bearer"})
    token, user = issued
    return TokenPublic(access_token=token, role=user.role.value)


@router.get("/me", response_model=UserPublic)
def read_me(user: CurrentUser) -> UserPublic:
    """The caller's account (``anonymous``/admin while no account exists)."""
    return UserPublic(name=user.name, role=user.role.value)
