"""Alembic revisions of the server's schema, oldest first (0001 is schema version 1)."""
