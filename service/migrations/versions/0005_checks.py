# ruff: noqa
"""checks: a check of a bench's calibration in force (verdict, the check's document, the proposed update)

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-29 07:40:00
"""

from alembic import op
import sqlalchemy as sa


revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "checks",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("bench", sa.String(length=64), nullable=True),
        sa.Column("service", sa.String(length=64), nullable=True),
        sa.Column("verdict", sa.String(length=16), nullable=True),
        sa.Column("calibration_id", sa.Integer(), nullable=True),
        sa.Column("calibration_run_id", sa.String(length=32), nullable=True),
        sa.Column("in_force", sa.JSON(), nullable=False),
        sa.Column("plan", sa.JSON(), nullable=True),
        sa.Column("dataset_dir", sa.Text(), nullable=False),
        sa.Column("result", sa.JSON(), nullable=True),
        sa.Column("update", sa.JSON(), nullable=True),
        sa.Column("applied_calibration_id", sa.Integer(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_checks_state", "checks", ["state"])
    op.create_index("ix_checks_created_at", "checks", ["created_at"])
    op.create_index("ix_checks_bench", "checks", ["bench"])
    op.create_index("ix_checks_service", "checks", ["service"])
    op.create_index("ix_checks_verdict", "checks", ["verdict"])


def downgrade() -> None:
    op.drop_table("checks")
