"""The first schema of the results database: analyses and results.

Revision ID: 0001
Revises:
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "analyses",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("unit_id", sa.String(128), nullable=False, index=True),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("run", sa.String(256), nullable=False),
        sa.Column("recording", sa.Text, nullable=False),
        sa.Column("recorded_utc", sa.String(40)),
        sa.Column("analysed_utc", sa.String(40), nullable=False),
        sa.Column("procedure", sa.String(128)),
        sa.Column("lot", sa.String(128), index=True),
        sa.Column("software_version", sa.String(64), nullable=False),
        sa.Column("spec", sa.Text),
        sa.Column("decision_rule", sa.String(16)),
        sa.Column("overall_verdict", sa.String(16)),
    )
    op.create_table(
        "results",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("analysis_id", sa.Integer, sa.ForeignKey("analyses.id", ondelete="CASCADE"),
                  nullable=False, index=True),
        sa.Column("parameter", sa.String(128), nullable=False, index=True),
        sa.Column("name_si", sa.String(128), nullable=False),
        sa.Column("value_si", sa.Float(53), nullable=False),
        sa.Column("u_si", sa.Float(53), nullable=False),
        sa.Column("value", sa.Float(53), nullable=False),
        sa.Column("u", sa.Float(53), nullable=False),
        sa.Column("unit", sa.String(32), nullable=False),
        sa.Column("k", sa.Float(53)),
        sa.Column("dof", sa.Float(53)),
        sa.Column("ci95_low", sa.Float(53)),
        sa.Column("ci95_high", sa.Float(53)),
        sa.Column("verdict", sa.String(16)),
        sa.Column("p_conform", sa.Float(53)),
    )


def downgrade() -> None:
    op.drop_table("results")
    op.drop_table("analyses")
