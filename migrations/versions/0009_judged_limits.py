"""The acceptance limits a calibration was judged against, kept with it: a certificate or run page read
later shows the limits its verdict came from, not those in force today (a limit changed since made a
FAIL certificate list every figure as PASS).

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-29
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('calibrations', schema=None) as b:
        b.add_column(sa.Column('limits', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('calibrations', schema=None) as b:
        b.drop_column('limits')
