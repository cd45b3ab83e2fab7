"""Web sessions: the pages' cookie carries a random session token with an expiry, stored hashed and
tied to the key that logged in, instead of the API key itself.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'web_sessions',
        sa.Column('token_hash', sa.String(64), primary_key=True),
        sa.Column('key_id', sa.Integer(), sa.ForeignKey('api_keys.id', ondelete='CASCADE'), nullable=False),
        sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
        sa.Column('expires_at', sa.DateTime(timezone=True), nullable=False))
    op.create_index('ix_web_sessions_key_id', 'web_sessions', ['key_id'])


def downgrade() -> None:
    op.drop_index('ix_web_sessions_key_id', 'web_sessions')
    op.drop_table('web_sessions')
