"""The right unit: each station's serial policy (what a run does when a unit reports another serial
number than the one typed: prompt, refuse or trust-typed), and on each calibration the typed and
identified serial numbers with how they were settled.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-25
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('stations', schema=None) as b:
        b.add_column(sa.Column('serial_policy', sa.String(16), nullable=False, server_default='prompt'))
    with op.batch_alter_table('calibrations', schema=None) as b:
        b.add_column(sa.Column('identity', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('calibrations', schema=None) as b:
        b.drop_column('identity')
    with op.batch_alter_table('stations', schema=None) as b:
        b.drop_column('serial_policy')
