"""Extra columns of imported recordings: kept (RECORDING.md), one row per column and slot with its
values in sample order, and exported again.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'sample_extras',
        sa.Column('id', sa.Integer(), primary_key=True),
        sa.Column('run_id', sa.Integer(), sa.ForeignKey('runs.id', ondelete='CASCADE'), nullable=False),
        sa.Column('slot', sa.Integer(), nullable=False),
        sa.Column('name', sa.String(64), nullable=False),
        sa.Column('values', sa.JSON(), nullable=False))
    op.create_index('ix_sample_extras_run_id', 'sample_extras', ['run_id'])


def downgrade() -> None:
    op.drop_index('ix_sample_extras_run_id', 'sample_extras')
    op.drop_table('sample_extras')
