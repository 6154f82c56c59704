"""Fitted analyses are kept: ``fitted_analysis``, one row per (study, kind, settings, data
version, analysis code version).

Revision ID: 0024
Revises: 0023
Create Date: 2026-12-07

The analysis pages, ``mixed_models.json`` and the report fitted every model again on every
request (12-28 s for the mixed models page of the 8-participant demo, issue 49). A fitted result
is now stored under the SHA-256 of what it depends on, so that every worker and the next start
reuse it (app.services.analysis_views.fit_cache). The table starts empty: results are fitted
when first asked for.

Downgrade drops the table (it holds nothing that cannot be fitted again).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0024"
down_revision: str | None = "0023"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "fitted_analysis",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.Integer(), nullable=False),
        sa.Column("key", sa.String(64), nullable=False),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("settings", sa.String(255), nullable=False),
        sa.Column("data_version", sa.String(64), nullable=False),
        sa.Column("code_version", sa.String(64), nullable=False),
        sa.Column("payload", sa.LargeBinary(), nullable=False),
        sa.Column("seconds", sa.Double(), nullable=False),
        sa.Column("fitted_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["study_id"], ["study.id"], name=op.f("fk_fitted_analysis_study_id_study")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fitted_analysis")),
        sa.UniqueConstraint("key", name=op.f("uq_fitted_analysis_key")),
    )
    op.create_index(
        op.f("ix_fitted_analysis_study_id"), "fitted_analysis", ["study_id"], unique=False
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_fitted_analysis_study_id"), table_name="fitted_analysis")
    op.drop_table("fitted_analysis")
