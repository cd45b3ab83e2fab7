"""calibrations.figures: the numbers the acceptance limits judge, kept beside the full JSON so that
history queries and trend plots need not load every calibration's document.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('calibrations', schema=None) as batch_op:
        batch_op.add_column(sa.Column('figures', sa.JSON(), nullable=True))
    # backfill rows stored before this column existed
    from service.store import figures
    conn = op.get_bind()
    cal = sa.table('calibrations', sa.column('id', sa.Integer), sa.column('data', sa.JSON), sa.column('figures', sa.JSON))
    for cid, data in conn.execute(sa.select(cal.c.id, cal.c.data)).all():
        conn.execute(sa.update(cal).where(cal.c.id == cid).values(figures=figures(data)))


def downgrade() -> None:
    with op.batch_alter_table('calibrations', schema=None) as batch_op:
        batch_op.drop_column('figures')
