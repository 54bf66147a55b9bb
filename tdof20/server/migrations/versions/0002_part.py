"""Schema version 2: a submission names the part it was scored on (``part``: 'test', or 'val'
for a protocol's validation part, whose per-image detail may be shown); the queue's claim looks
jobs up by (state, id). Rows of version 1 were all test submissions.

Revision ID: 0002
Revises: 0001
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("submissions", sa.Column("part", sa.String(8), nullable=False, server_default="test"))
    op.create_index("ix_jobs_state_id", "jobs", ["state", "id"])
    op.execute(sa.text("UPDATE meta SET value = '2' WHERE key = 'schema_version'"))
