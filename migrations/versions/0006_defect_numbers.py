"""defect numbers (one per session and source, in order along the structure) and defects
drawn by hand

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24 09:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("defects", schema=None) as batch_op:
        batch_op.add_column(sa.Column("number", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("drawn_by", sa.String(length=200), nullable=True))
    # existing defects: numbered as the reports listed them (across, then along the structure)
    op.execute(
        """
        UPDATE defects SET number = (
            SELECT n FROM (
                SELECT id, ROW_NUMBER() OVER (
                    PARTITION BY session_id, source
                    ORDER BY (world_x_m IS NULL OR world_y_m IS NULL),
                             COALESCE(world_y_m, 0), COALESCE(world_x_m, 0), id
                ) AS n
                FROM defects
            ) AS ranked WHERE ranked.id = defects.id
        )
        """
    )


def downgrade() -> None:
    with op.batch_alter_table("defects", schema=None) as batch_op:
        batch_op.drop_column("drawn_by")
        batch_op.drop_column("number")
