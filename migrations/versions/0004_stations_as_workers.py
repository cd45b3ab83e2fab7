"""Stations as workers: the station's state, its worker and heartbeat on its row; each run's live
view (pause request, waiting prompts, progress) on its row; run events and operator commands as
tables, so that any API process can answer and stream and a worker in another process can obey;
on PostgreSQL, procrastinate's job-queue schema (the version pinned in pyproject.toml).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('stations', schema=None) as b:
        b.add_column(sa.Column('state', sa.String(16), nullable=False, server_default='idle'))
        b.add_column(sa.Column('reason', sa.Text(), nullable=True))
        b.add_column(sa.Column('run_id', sa.Integer(), nullable=True))
        b.add_column(sa.Column('batch_id', sa.Integer(), nullable=True))
        b.add_column(sa.Column('worker', sa.String(128), nullable=True))
        b.add_column(sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=True))
        b.add_column(sa.Column('reset', sa.JSON(), nullable=True))
    with op.batch_alter_table('runs', schema=None) as b:
        b.add_column(sa.Column('pause_requested', sa.Boolean(), nullable=False, server_default=sa.false()))
        b.add_column(sa.Column('prompts', sa.JSON(), nullable=False, server_default='{}'))
        b.add_column(sa.Column('progress', sa.JSON(), nullable=True))
    big = sa.BigInteger().with_variant(sa.Integer(), 'sqlite')
    op.create_table(
        'run_events',
        sa.Column('id', big, primary_key=True),
        sa.Column('run_id', sa.Integer(), sa.ForeignKey('runs.id', ondelete='CASCADE'), nullable=False),
        sa.Column('kind', sa.String(16), nullable=False),
        sa.Column('data', sa.JSON(), nullable=False),
        sa.Column('created_at', sa.DateTime(timezone=True), nullable=False))
    op.create_index('ix_run_events_run_id', 'run_events', ['run_id'])
    op.create_table(
        'run_commands',
        sa.Column('id', sa.Integer(), primary_key=True),
        sa.Column('run_id', sa.Integer(), sa.ForeignKey('runs.id', ondelete='CASCADE'), nullable=False),
        sa.Column('kind', sa.String(16), nullable=False),
        sa.Column('data', sa.JSON(), nullable=False),
        sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
        sa.Column('taken_at', sa.DateTime(timezone=True), nullable=True))
    op.create_index('ix_run_commands_run_id', 'run_commands', ['run_id'])
    bind = op.get_bind()
    if bind.dialect.name == 'postgresql':
        exists = bind.exec_driver_sql("SELECT to_regclass('procrastinate_jobs')").scalar()
        if exists is None:
            from procrastinate.schema import SchemaManager  # the library's own schema, not our code
            with bind.connection.cursor() as cur:  # no parameters: its '%' are not placeholders
                cur.execute(SchemaManager.get_schema())


def downgrade() -> None:
    op.drop_index('ix_run_commands_run_id', 'run_commands')
    op.drop_table('run_commands')
    op.drop_index('ix_run_events_run_id', 'run_events')
    op.drop_table('run_events')
    with op.batch_alter_table('runs', schema=None) as b:
        for c in ('progress', 'prompts', 'pause_requested'):
            b.drop_column(c)
    with op.batch_alter_table('stations', schema=None) as b:
        for c in ('reset', 'heartbeat_at', 'worker', 'batch_id', 'run_id', 'reason', 'state'):
            b.drop_column(c)
