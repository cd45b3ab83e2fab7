"""Alembic environment: runs on the connection the service hands over (service.db.upgrade), or on
``COMPASSCAL_DATABASE_URL`` / the default SQLite file when called from the alembic command line."""

from __future__ import annotations

from alembic import context

from service.db import Base, make_engine

target_metadata = Base.metadata


def run() -> None:
    connection = context.config.attributes.get("connection")
    if connection is not None:
        context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
        return
    with make_engine().begin() as conn:
        context.configure(connection=conn, target_metadata=target_metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()


run()
