"""Analyses as jobs: an analysis row exists from the request on (``queued``, ``running``, then
``completed`` with its result or ``failed`` with the reason), with its slot, what was asked, its
progress and a version the server-sent events use as their id. Rows written before are completed.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('analyses', schema=None) as b:
        b.alter_column('report', existing_type=sa.JSON(), nullable=True)
        b.add_column(sa.Column('status', sa.String(16), nullable=False, server_default='completed'))
        b.add_column(sa.Column('slot', sa.Integer(), nullable=True))
        b.add_column(sa.Column('request', sa.JSON(), nullable=False, server_default='{}'))
        b.add_column(sa.Column('progress', sa.JSON(), nullable=True))
        b.add_column(sa.Column('reason', sa.Text(), nullable=True))
        b.add_column(sa.Column('started_at', sa.DateTime(timezone=True), nullable=True))
        b.add_column(sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True))
        b.add_column(sa.Column('version', sa.Integer(), nullable=False, server_default='0'))
    op.create_index('ix_analyses_run_id', 'analyses', ['run_id'])


def downgrade() -> None:
    op.drop_index('ix_analyses_run_id', 'analyses')
    with op.batch_alter_table('analyses', schema=None) as b:
        for c in ('version', 'finished_at', 'started_at', 'reason', 'progress', 'request', 'slot', 'status'):
            b.drop_column(c)
