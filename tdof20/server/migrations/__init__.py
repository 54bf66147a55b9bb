"""The server's schema migrations (alembic): ``versions/`` holds one revision per schema version,
applied in order by :func:`tdof20.server.db.init_db` when the server or a worker starts."""
