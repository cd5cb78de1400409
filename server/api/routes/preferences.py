"""What each user keeps of the dashboard across browsers and sessions: the telemetry fields
they plot, the Drive page's panel layout. A JSON object per account, merged key by key."""

from __future__ import annotations

import json
from http import HTTPStatus
from typing import Any

from fastapi import APIRouter, Body, HTTPException
from sqlalchemy.exc import IntegrityError

from server.api.deps import CurrentUser, SessionDep
from server.storage.models import UserPreferences

MAX_BYTES = 16 * 1024  # a user's preferences, as JSON
MAX_KEYS = 64
MAX_KEY_LENGTH = 100

router = APIRouter(prefix="/api/auth/me", tags=["auth"])


@router.get("/preferences")
def read_preferences(db: SessionDep, user: CurrentUser) -> dict[str, Any]:
    """The caller's preferences (``{}`` before they kept any)."""
    row = db.get(UserPreferences, user.name)
    return dict(row.data) if row is not None else {}


@router.patch("/preferences")
def update_preferences(
    db: SessionDep,
    user: CurrentUser,
    changes: dict[str, Any] = Body(
        description="keys to set (a value of null removes the key); others are kept",
        examples=[{"plot_fields": ["battery_v.main", "wheel_speed_mps[0]"]}],
    ),
) -> dict[str, Any]:
    """Set some of the caller's preferences, keeping the rest; the whole object stays
    within 16 KiB of JSON and 64 keys (413 / 422 otherwise, nothing changed)."""
    if any(not k or len(k) > MAX_KEY_LENGTH for k in changes):
        raise HTTPException(
            HTTPStatus.UNPROCESSABLE_ENTITY,
            f"preference names are 1 to {MAX_KEY_LENGTH} characters",
        )
    for _ in range(2):  # a first write may race another tab's: the second sees its row
        row = db.get(UserPreferences, user.name)
        merged = dict(row.data) if row is not None else {}
        for k, v in changes.items():
            if v is None:
                merged.pop(k, None)
            else:
                merged[k] = v
        if len(merged) > MAX_KEYS:
            raise HTTPException(
                HTTPStatus.UNPROCESSABLE_ENTITY, f"at most {MAX_KEYS} preferences a user"
            )
        try:
            size = len(json.dumps(merged, allow_nan=False).encode())
        except ValueError:
            raise HTTPException(
                HTTPStatus.UNPROCESSABLE_ENTITY, "preferences are numbers, not NaN or infinity"
            ) from None
        if size > MAX_BYTES:
            raise HTTPException(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                f"preferences would take {size} bytes; at most {MAX_BYTES}",
            )
        if row is None:
            db.add(UserPreferences(user_name=user.name, data=merged))
        else:
            row.data = merged
        try:
            db.commit()
            return merged
        except IntegrityError:
            db.rollback()
    raise HTTPException(HTTPStatus.CONFLICT, "preferences changed meanwhile: try again")
