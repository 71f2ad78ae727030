# ruff: noqa
"""runs: the prediction of a run's plan before motion (predicted std per method and combination, motion time)

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-27 23:20:00
"""

from alembic import op
import sqlalchemy as sa


revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("prediction", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs", schema=None) as batch_op:
        batch_op.drop_column("prediction")
