"""frame and cloud payloads in per-session segment files: byte offset of each

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-22 06:10:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    for table in ("frames", "clouds"):
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.add_column(sa.Column("data_offset", sa.BigInteger(), nullable=True))


def downgrade() -> None:
    for table in ("frames", "clouds"):
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.drop_column("data_offset")
