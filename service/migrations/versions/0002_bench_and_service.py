# ruff: noqa
"""runs.service (the service executing a run, named by its bench) and indexes on the bench columns: several services
(one per bench) can share one database

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21 10:45:00
"""

from alembic import op
import sqlalchemy as sa


revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("service", sa.String(length=64), nullable=True))
        batch_op.create_index(batch_op.f("ix_runs_service"), ["service"], unique=False)
        batch_op.create_index(batch_op.f("ix_runs_bench"), ["bench"], unique=False)
    with op.batch_alter_table("calibrations", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_calibrations_bench"), ["bench"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("calibrations", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_calibrations_bench"))
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_runs_bench"))
        batch_op.drop_index(batch_op.f("ix_runs_service"))
        batch_op.drop_column("service")
