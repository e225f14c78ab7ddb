"""The registry's schema comes from its Alembic migrations (run from code, no alembic.ini), and a
database they create has exactly the ORM's schema — on SQLite and on PostgreSQL."""
import sqlalchemy as sa
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from inclinometer_calib.fleet import registry as rg


def _diff(engine, metadata):
    with engine.connect() as conn:
        return compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True,
                                                                       "compare_server_default": True}), metadata)


def test_migrated_database_has_exactly_the_orm_schema(db_url):
    with rg.Registry(db_url) as reg:
        assert rg.current_revision(reg.engine) == rg.head_revision() == "0001"
        assert _diff(reg.engine, rg.Base.metadata) == []
        names = set(sa.inspect(reg.engine).get_table_names())
        assert {"probes", "calibrations", "alembic_version"} <= names


def test_the_comparison_sees_a_schema_that_differs(db_url):
    """The check above can fail: an ORM with one more column or index than the migration made is a diff."""
    with rg.Registry(db_url) as reg:
        md = sa.MetaData()
        for t in rg.Base.metadata.tables.values():
            t.to_metadata(md)
        md.tables["probes"].append_column(sa.Column("retired", sa.Boolean, nullable=True))
        sa.Index("ix_calibrations_method", md.tables["calibrations"].c.method)
        kinds = sorted(d[0] if isinstance(d, tuple) else d[0][0] for d in _diff(reg.engine, md))
        assert kinds == ["add_column", "add_index"]


def test_downgrade_to_base_and_upgrade_again(db_url):
    with rg.Registry(db_url) as reg:
        with reg.engine.begin() as conn:
            command.downgrade(rg.alembic_config(conn), "base")
        assert set(sa.inspect(reg.engine).get_table_names()) <= {"alembic_version"}
        assert rg.current_revision(reg.engine) is None
        rg.migrate(reg.engine)
        assert _diff(reg.engine, rg.Base.metadata) == []
        reg.add_probe("SN-1")            # usable after the round trip
        assert reg.probe("SN-1").calibration_interval_days == rg.DEFAULT_INTERVAL_DAYS
