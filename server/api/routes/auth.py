"""Tokens for REST clients (OAuth2 password flow) and who the caller is."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.security import OAuth2PasswordRequestForm
from pydantic import BaseModel

from server.api.accounts import accounts_exist, issue_token, revoke_token
from server.api.deps import CurrentUser, SessionDep, StateDep, oauth2

router = APIRouter(prefix="/api/auth", tags=["auth"])


class TokenPublic(BaseModel):
    access_token: str
    token_type: str = "bearer"
    role: str


class UserPublic(BaseModel):
    name: str
    role: str


@router.post("/token", response_model=TokenPublic)
async def create_token(
    state: StateDep, request: Request, form: Annotated[OAuth2PasswordRequestForm, Depends()]
) -> TokenPublic:
    """Exchange a user name and password for a bearer token (429 after repeated wrong
    passwords from one client, for one user or over all, until the throttle's window has
    passed; 429 too while one client address, or the whole station, asks for more
    password checks a second than it allows)."""
    client = request.client.host if request.client else "?"
    wait = state.logins.retry_after(client, form.username)
    if wait > 0:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            f"too many wrong passwords; try again in {wait:.0f} s",
            headers={"Retry-After": str(max(1, round(wait)))},
        )
    if not state.passwords.take_for(client):
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            "too many sign-ins at once; try again in a few seconds",
            headers={"Retry-After": "5"},
        )
    issued = await state.passwords.run(issue_token, state.factory, form.username, form.password)
    if issued is None:
        state.logins.failed(client, form.username)
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "wrong user name or password",
            headers={"WWW-Authenticate": "Bearer"},
        )
    state.logins.succeeded(client, form.username)
    state.passwords.refund(client)
    token, user = issued
    return TokenPublic(access_token=token, role=user.role.value)


@router.delete("/token", status_code=status.HTTP_204_NO_CONTENT)
def delete_token(db: SessionDep, token: Annotated[str | None, Depends(oauth2)]) -> None:
    """Sign out: the bearer token the request carries stops working at once (other tokens
    of the same user, e.g. another browser's, stay valid)."""
    if not revoke_token(db, token) and accounts_exist(db):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "a valid bearer token is required",
            headers={"WWW-Authenticate": "Bearer"},
        )


@router.get("/me", response_model=UserPublic)
def read_me(user: CurrentUser) -> UserPublic:
    """The caller's account (``anonymous``/admin while no account exists)."""
    return UserPublic(name=user.name, role=user.role.value)
