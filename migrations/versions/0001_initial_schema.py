"""initial schema

Revision ID: 0001
Revises: 
Create Date: 2026-11-22
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op


revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


# The acceptance limits a new database starts with (admin-editable afterwards).
DEFAULT_LIMITS = [
    {"name": "residual_rms_lsb", "marginal": 6.0, "fail": 15.0, "unit": "LSB",
     "description": "largest per-axis RMS of the model residuals"},
    # In-sample figures on the recording's pose means, so they include the recording's own noise
    # (about 0.01-0.02 deg per pose for 60 samples at 3 LSB): the limits sit above that floor.
    {"name": "heading_error_level_deg", "marginal": 0.05, "fail": 0.2, "unit": "deg",
     "description": "max heading error over the recording's level turn (pose means, noise included)"},
    {"name": "heading_error_tilted_deg", "marginal": 0.15, "fail": 0.5, "unit": "deg",
     "description": "max heading error over the recording's poses with pitch and roll up to 60 deg (pose means)"},
    {"name": "misalignment_deg", "marginal": 3.0, "fail": 6.0, "unit": "deg",
     "description": "largest angle between a sensor axis and its body axis"},
    {"name": "sensitivity_mismatch", "marginal": 0.08, "fail": 0.2, "unit": "ratio",
     "description": "largest relative difference of an axis's sensitivity from the three's mean"},
    {"name": "bias_lsb", "marginal": 1500.0, "fail": 4000.0, "unit": "LSB",
     "description": "magnitude of the magnetometer bias vector"},
]


def upgrade() -> None:
    op.create_table('api_keys',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('owner', sa.String(length=64), nullable=False),
    sa.Column('role', sa.String(length=16), nullable=False),
    sa.Column('key_hash', sa.String(length=64), nullable=False),
    sa.Column('prefix', sa.String(length=12), nullable=False),
    sa.Column('revoked', sa.Boolean(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id'),
    sa.UniqueConstraint('key_hash')
    )
    op.create_table('audit_log',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('owner', sa.String(length=64), nullable=False),
    sa.Column('action', sa.String(length=64), nullable=False),
    sa.Column('target', sa.String(length=128), nullable=False),
    sa.Column('detail', sa.JSON(), nullable=True),
    sa.PrimaryKeyConstraint('id')
    )
    op.create_table('devices',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('serial', sa.String(length=64), nullable=False),
    sa.Column('model', sa.String(length=64), nullable=True),
    sa.Column('firmware', sa.String(length=32), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id'),
    sa.UniqueConstraint('serial')
    )
    op.create_table('limits',
    sa.Column('name', sa.String(length=64), nullable=False),
    sa.Column('marginal', sa.Double(), nullable=False),
    sa.Column('fail', sa.Double(), nullable=False),
    sa.Column('unit', sa.String(length=16), nullable=False),
    sa.Column('description', sa.Text(), nullable=False),
    sa.PrimaryKeyConstraint('name')
    )
    op.bulk_insert(sa.table('limits', sa.column('name', sa.String), sa.column('marginal', sa.Float), sa.column('fail', sa.Float),
                            sa.column('unit', sa.String), sa.column('description', sa.Text)), DEFAULT_LIMITS)
    op.create_table('stations',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('name', sa.String(length=64), nullable=False),
    sa.Column('modbus', sa.String(length=256), nullable=False),
    sa.Column('compasses', sa.JSON(), nullable=False),
    sa.Column('time_scale', sa.Float(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id'),
    sa.UniqueConstraint('name')
    )
    op.create_table('batches',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('station_id', sa.Integer(), nullable=False),
    sa.Column('serials', sa.JSON(), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('operator', sa.String(length=64), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('summary', sa.JSON(), nullable=True),
    sa.ForeignKeyConstraint(['station_id'], ['stations.id'], ),
    sa.PrimaryKeyConstraint('id')
    )
    op.create_table('runs',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('station_id', sa.Integer(), nullable=True),
    sa.Column('batch_id', sa.Integer(), nullable=True),
    sa.Column('procedure', sa.String(length=32), nullable=False),
    sa.Column('procedure_version', sa.String(length=16), nullable=False),
    sa.Column('parameters', sa.JSON(), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('reason', sa.Text(), nullable=True),
    sa.Column('operator', sa.String(length=64), nullable=False),
    sa.Column('station_snapshot', sa.JSON(), nullable=True),
    sa.Column('serials', sa.JSON(), nullable=False),
    sa.Column('software_version', sa.String(length=32), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('table_seconds', sa.Double(), nullable=True),
    sa.Column('samples_count', sa.Integer(), nullable=False),
    sa.Column('meta', sa.JSON(), nullable=False),
    sa.ForeignKeyConstraint(['batch_id'], ['batches.id'], ),
    sa.ForeignKeyConstraint(['station_id'], ['stations.id'], ),
    sa.PrimaryKeyConstraint('id')
    )
    op.create_table('analyses',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('report', sa.JSON(), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], ),
    sa.PrimaryKeyConstraint('id')
    )
    op.create_table('calibrations',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('device_id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('slot', sa.Integer(), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('verdict', sa.String(length=16), nullable=False),
    sa.Column('reasons', sa.JSON(), nullable=False),
    sa.Column('method', sa.String(length=32), nullable=False),
    sa.Column('data', sa.JSON(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['device_id'], ['devices.id'], ),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], ),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('calibrations', schema=None) as batch_op:
        batch_op.create_index('ix_calibrations_device_created', ['device_id', 'created_at'], unique=False)

    op.create_table('samples',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('slot', sa.Integer(), nullable=False),
    sa.Column('t', sa.Double(), nullable=False),
    sa.Column('step', sa.String(length=32), nullable=False),
    sa.Column('psi_t', sa.Double(), nullable=False),
    sa.Column('theta_t', sa.Double(), nullable=False),
    sa.Column('phi_t', sa.Double(), nullable=False),
    sa.Column('mx', sa.Double(), nullable=False),
    sa.Column('my', sa.Double(), nullable=False),
    sa.Column('mz', sa.Double(), nullable=False),
    sa.Column('ax', sa.Double(), nullable=True),
    sa.Column('ay', sa.Double(), nullable=True),
    sa.Column('az', sa.Double(), nullable=True),
    sa.Column('temp_c', sa.Double(), nullable=True),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id')
    )
    with op.batch_alter_table('samples', schema=None) as batch_op:
        batch_op.create_index('ix_samples_run_slot', ['run_id', 'slot', 'id'], unique=False)



def downgrade() -> None:
    with op.batch_alter_table('samples', schema=None) as batch_op:
        batch_op.drop_index('ix_samples_run_slot')

    op.drop_table('samples')
    with op.batch_alter_table('calibrations', schema=None) as batch_op:
        batch_op.drop_index('ix_calibrations_device_created')

    op.drop_table('calibrations')
    op.drop_table('analyses')
    op.drop_table('runs')
    op.drop_table('batches')
    op.drop_table('stations')
    op.drop_table('limits')
    op.drop_table('devices')
    op.drop_table('audit_log')
    op.drop_table('api_keys')
