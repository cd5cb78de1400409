"""a session's end: the seq of its robot's SESSION_END, and a database rule that an ended
session never reopens (status back to live, or its end moved, is refused by a trigger)

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-28 05:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

REFUSAL = "an ended session cannot reopen or move its end"

SQLITE_TRIGGER = f"""
CREATE TRIGGER session_stays_ended BEFORE UPDATE OF status, end_seq ON inspection_sessions
WHEN OLD.status = 'ended' AND (
    NEW.status <> 'ended' OR (OLD.end_seq IS NOT NULL AND NEW.end_seq IS NOT OLD.end_seq)
)
BEGIN SELECT RAISE(ABORT, '{REFUSAL}'); END
"""

POSTGRES_FUNCTION = f"""
CREATE FUNCTION session_stays_ended() RETURNS trigger AS $$
BEGIN
    IF OLD.status = 'ended' AND (
        NEW.status <> 'ended'
        OR (OLD.end_seq IS NOT NULL AND NEW.end_seq IS DISTINCT FROM OLD.end_seq)
    ) THEN
        RAISE EXCEPTION '{REFUSAL}' USING ERRCODE = 'check_violation';
    END IF;
    RETURN NEW;
END $$ LANGUAGE plpgsql
"""
POSTGRES_TRIGGER = """
CREATE TRIGGER session_stays_ended BEFORE UPDATE OF status, end_seq ON inspection_sessions
FOR EACH ROW EXECUTE FUNCTION session_stays_ended()
"""


def upgrade() -> None:
    with op.batch_alter_table("inspection_sessions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("end_seq", sa.BigInteger(), nullable=True))
    # the seq of the SESSION_END each ended session already holds
    op.execute(
        "UPDATE inspection_sessions SET end_seq = (SELECT max(r.seq) FROM received_messages r "
        "WHERE r.session_id = inspection_sessions.id AND r.type = 'SESSION_END')"
    )
    if op.get_bind().dialect.name == "postgresql":
        op.execute(POSTGRES_FUNCTION)
        op.execute(POSTGRES_TRIGGER)
    else:
        op.execute(SQLITE_TRIGGER)


def downgrade() -> None:
    op.execute(
        "DROP TRIGGER IF EXISTS session_stays_ended"
        + (" ON inspection_sessions" if op.get_bind().dialect.name == "postgresql" else "")
    )
    if op.get_bind().dialect.name == "postgresql":
        op.execute("DROP FUNCTION IF EXISTS session_stays_ended()")
    with op.batch_alter_table("inspection_sessions", schema=None) as batch_op:
        batch_op.drop_column("end_seq")
