"""Robots (admin role): list, register (the token is shown once), revoke."""

from __future__ import annotations

import secrets
from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, status
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import func, select

from server.api.deps import SessionDep, StateDep, require
from server.api.schemas import Text
from server.errors import NotFound
from server.link.robots import create_robot
from server.storage.models import InspectionSession, Robot, Role

router = APIRouter(
    prefix="/api/robots", tags=["robots"], dependencies=[Depends(require(Role.admin))]
)
REVOKED = "revoked:"


class RobotRow(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    name: str
    created_at: datetime
    revoked: bool = False
    sessions: int = 0
    last_session_at: datetime | None = None


class RobotCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Annotated[Text, Field(min_length=1, max_length=200)]


class RobotToken(BaseModel):
    name: str
    token: str = Field(description="the robot's bearer token: shown this once, never again")


@router.get("", response_model=list[RobotRow])
def read_robots(db: SessionDep) -> list[RobotRow]:
    """Every registered robot with how many sessions it recorded and when it last did."""
    rows = db.execute(
        select(Robot, func.count(InspectionSession.id), func.max(InspectionSession.started_at))
        .outerjoin(InspectionSession, InspectionSession.robot_id == Robot.id)
        .group_by(Robot.id)
        .order_by(Robot.name)
    )
    return [
        RobotRow(
            name=r.name,
            created_at=r.created_at,
            revoked=r.token_hash.startswith(REVOKED),
            sessions=n,
            last_session_at=last,
        )
        for r, n, last in rows
    ]


@router.post("", response_model=RobotToken, status_code=status.HTTP_201_CREATED)
def add_robot(state: StateDep, body: RobotCreate) -> RobotToken:
    """Register a robot; its token is in the answer and nowhere else."""
    try:
        token = create_robot(state.factory, body.name)
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, str(exc)) from None
    return RobotToken(name=body.name.strip(), token=token)


@router.delete("/{name}", status_code=status.HTTP_204_NO_CONTENT)
def revoke_robot(db: SessionDep, name: str) -> None:
    """Revoke a robot's token: it cannot connect again (its sessions stay, under its name);
    register it under a new name for a new token."""
    robot = db.scalar(select(Robot).where(Robot.name == name))
    if robot is None:
        raise NotFound(f"no robot named {name!r}")
    robot.token_hash = REVOKED + secrets.token_hex(16)
    db.commit()
