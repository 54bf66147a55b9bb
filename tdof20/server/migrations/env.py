"""Alembic's entry point for the server's migrations. :func:`tdof20.server.db.init_db` runs it
with a connection already inside a transaction (SQLite: the writer lock; PostgreSQL: an advisory
lock), so every migration of one start applies together or not at all, and two processes starting
at once upgrade the database once."""

from alembic import context

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=None)
with context.begin_transaction():  # the caller's transaction (nothing new begins)
    context.run_migrations()
