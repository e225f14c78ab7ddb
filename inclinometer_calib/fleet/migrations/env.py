"""Alembic environment of the fleet registry (run from code by ``registry.migrate``).

The connection comes from ``config.attributes["connection"]`` (the registry's own, inside its
transaction); without one, from the ``sqlalchemy.url`` main option (e.g. to generate a revision).
SQLite gets batch mode, so that later revisions can alter its tables.
"""
from alembic import context
from sqlalchemy import create_engine

from inclinometer_calib.fleet.registry import Base

config = context.config
target_metadata = Base.metadata


def _run(connection):
    context.configure(connection=connection, target_metadata=target_metadata,
                      render_as_batch=connection.dialect.name == "sqlite", compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_offline():
    context.configure(url=config.get_main_option("sqlalchemy.url"), target_metadata=target_metadata,
                      literal_binds=True, dialect_opts={"paramstyle": "named"})
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online():
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = create_engine(config.get_main_option("sqlalchemy.url"))
    with engine.begin() as conn:
        _run(conn)
    engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
