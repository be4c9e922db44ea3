"""Alembic environment of the results database: run online on the connection that
rigctl.recording.results_db.open_db passes in ``config.attributes["connection"]`` (or on the URL of the
config's ``sqlalchemy.url``, for the ``alembic`` command line)."""
from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine

config = context.config
conn = config.attributes.get("connection")
if conn is None:
    engine = create_engine(config.get_main_option("sqlalchemy.url"))
    with engine.begin() as c:
        context.configure(connection=c, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
else:
    context.configure(connection=conn, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()
