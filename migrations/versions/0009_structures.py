"""structures and their AASHTO elements; a session inspects a structure (its world frame
placed in the structure's by a datum); a reviewer's AASHTO defect code on a defect

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-28 12:30:00
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None
FK_NAME = "inspection_sessions_structure_id_fkey"  # PostgreSQL's own name for it


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
    # plain ALTER TABLE ADD COLUMN: a batch copy of inspection_sessions on SQLite would drop
    # the trigger of 0008 that keeps an ended session ended
    if op.get_bind().dialect.name == "sqlite":
        op.execute(
            "ALTER TABLE inspection_sessions ADD COLUMN structure_id INTEGER "
            "REFERENCES structures (id)"
        )
    else:
        op.add_column("inspection_sessions", sa.Column("structure_id", sa.Integer, nullable=True))
        op.create_foreign_key(
            FK_NAME,
            "inspection_sessions",
            "structures",
            ["structure_id"],
            ["id"],
        )
    op.add_column("inspection_sessions", sa.Column("datum", sa.JSON, nullable=True))
    op.add_column("defects", sa.Column("defect_code", sa.Integer, nullable=True))


def downgrade() -> None:
    op.drop_column("defects", "defect_code")
    op.drop_column("inspection_sessions", "datum")
    if op.get_bind().dialect.name == "sqlite":
        # SQLite drops a column under a foreign key only by copying the table, which drops
        # its triggers: 0008's is made again
        with op.batch_alter_table("inspection_sessions") as batch:
            batch.drop_column("structure_id")
        op.execute(_session_end_trigger())
    else:
        op.drop_constraint(FK_NAME, "inspection_sessions", type_="foreignkey")
        op.drop_column("inspection_sessions", "structure_id")
    op.drop_table("elements")
    op.drop_table("structures")


def _session_end_trigger() -> str:
    """Migration 0008's SQLite trigger."""
    path = Path(__file__).with_name("0008_session_end.py")
    spec = importlib.util.spec_from_file_location("session_end_0008", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return str(module.SQLITE_TRIGGER)
