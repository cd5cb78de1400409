"""structures and their AASHTO elements; a session inspects a structure (its world frame
placed in the structure's by a datum); a reviewer's AASHTO defect code on a defect

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-28 12:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "structures",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.String(200), nullable=False, unique=True),
        sa.Column("owner_id", sa.String(100), nullable=False, server_default=""),
        sa.Column("location", sa.Text, nullable=False, server_default=""),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_table(
        "elements",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column(
            "structure_id",
            sa.Integer,
            sa.ForeignKey("structures.id", ondelete="CASCADE"),
            nullable=False,
            index=True,
        ),
        sa.Column("number", sa.Integer, nullable=False),
        sa.Column("name", sa.String(200), nullable=False, server_default=""),
        sa.Column("quantity", sa.Double(), nullable=False),
        sa.Column("x0", sa.Double(), nullable=False),
        sa.Column("y0", sa.Double(), nullable=False),
        sa.Column("x1", sa.Double(), nullable=False),
        sa.Column("y1", sa.Double(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    with op.batch_alter_table("inspection_sessions") as batch:
        batch.add_column(sa.Column("structure_id", sa.Integer, nullable=True))
        batch.add_column(sa.Column("datum", sa.JSON, nullable=True))
        batch.create_foreign_key(
            "fk_sessions_structure", "structures", ["structure_id"], ["id"], ondelete="SET NULL"
        )
    with op.batch_alter_table("defects") as batch:
        batch.add_column(sa.Column("defect_code", sa.Integer, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("defects") as batch:
        batch.drop_column("defect_code")
    with op.batch_alter_table("inspection_sessions") as batch:
        batch.drop_constraint("fk_sessions_structure", type_="foreignkey")
        batch.drop_column("datum")
        batch.drop_column("structure_id")
    op.drop_table("elements")
    op.drop_table("structures")
