"""samples.psi_t, theta_t, phi_t nullable: a recording without table angles (a hand-held one, or a
foreign import) is stored with NULL angles instead of being refused.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None

ANGLES = ('psi_t', 'theta_t', 'phi_t')


def upgrade() -> None:
    with op.batch_alter_table('samples', schema=None) as batch_op:
        for name in ANGLES:
            batch_op.alter_column(name, existing_type=sa.Double(), nullable=True)


def downgrade() -> None:
    # never delete recorded samples to go back: refuse while recordings without angles exist
    n = op.get_bind().execute(sa.text("SELECT count(*) FROM samples WHERE psi_t IS NULL OR theta_t IS NULL "
                                      "OR phi_t IS NULL")).scalar()
    if n:
        raise RuntimeError(f"{n} samples have no table angles; export and delete their runs before downgrading")
    with op.batch_alter_table('samples', schema=None) as batch_op:
        for name in ANGLES:
            batch_op.alter_column(name, existing_type=sa.Double(), nullable=False)
