"""Schema version 3: a submission's method links (``paper``, ``code``) and the versions its score
is on (``scorer_version``, ``dataset_version``: None for one scored before, which ``tdof20 serve
rescore`` scores again); ``held_back``: per protocol, the part of its test images kept for the final
private leaderboard (how it was chosen, the images, when the operator revealed it). Rows of
version 2 get empty links and no versions.

Revision ID: 0003
Revises: 0002
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("submissions") as b:
        b.add_column(sa.Column("paper", sa.Text, nullable=False, server_default=""))
        b.add_column(sa.Column("code", sa.Text, nullable=False, server_default=""))
        b.add_column(sa.Column("scorer_version", sa.String(64)))
        b.add_column(sa.Column("dataset_version", sa.String(64)))
    op.create_table(
        "held_back",
        sa.Column("split", sa.String(32), primary_key=True),
        sa.Column("by", sa.String(8), nullable=False),
        sa.Column("fraction", sa.Float, nullable=False),
        sa.Column("seed", sa.String(64), nullable=False),
        sa.Column("images", sa.Text, nullable=False),
        sa.Column("n_images", sa.Integer, nullable=False),
        sa.Column("digest", sa.String(64), nullable=False),
        sa.Column("created", sa.Float, nullable=False),
        sa.Column("revealed", sa.Float))
    op.execute(sa.text("UPDATE meta SET value = '3' WHERE key = 'schema_version'"))
