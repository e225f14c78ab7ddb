"""Initial schema of the fleet registry: probes (by serial) and their calibration records.

Revision ID: 0001
Revises:
Create Date: 2026-11-23

A migration is frozen: it spells its types out (``registry.UTCDateTime`` is stored as
``DateTime(timezone=True)``) instead of importing the ORM, which later revisions change.
"""
from typing import Sequence, Union

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: Union[str, Sequence[str], None] = None
branch_labels: Union[str, Sequence[str], None] = None
depends_on: Union[str, Sequence[str], None] = None


def upgrade() -> None:
    op.create_table(
        "probes",
        sa.Column("serial", sa.String(length=64), nullable=False),
        sa.Column("model", sa.String(length=200), nullable=False),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("calibration_interval_days", sa.Float(), nullable=False),
        sa.Column("created", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("serial", name=op.f("pk_probes")),
    )
    op.create_table(
        "calibrations",
        sa.Column("id", sa.String(length=64), nullable=False),
        sa.Column("probe_serial", sa.String(length=64), nullable=False),
        sa.Column("calibrated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("method", sa.Text(), nullable=False),
        sa.Column("model_description", sa.Text(), nullable=False),
        sa.Column("site", sa.JSON(), nullable=False),
        sa.Column("record_yaml", sa.Text(), nullable=False),
        sa.Column("operator_note", sa.Text(), nullable=False),
        sa.Column("raw_log_sha256", sa.String(length=64), nullable=False),
        sa.Column("uncertainty", sa.JSON(), nullable=False),
        sa.Column("created", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["probe_serial"], ["probes.serial"],
                                name=op.f("fk_calibrations_probe_serial_probes"), ondelete="RESTRICT"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_calibrations")),
        sa.UniqueConstraint("probe_serial", "calibrated_at", name="uq_calibrations_probe_serial_calibrated_at"),
    )
    op.create_index("ix_calibrations_calibrated_at", "calibrations", ["calibrated_at"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_calibrations_calibrated_at", table_name="calibrations")
    op.drop_table("calibrations")
    op.drop_table("probes")
