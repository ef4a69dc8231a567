"""A private PostgreSQL cluster for a test: started with scripts/postgres.sh in a new folder,
stopped and removed afterwards, also when the test fails.

The ``postgres`` fixture (test/conftest.py) gives one cluster per test module. How the registry
uses it: docs/registry.md.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile

from drvs.testing.harness import REPO

__all__ = ['PostgresCluster', 'shared_registry']

SCRIPT = REPO / 'scripts' / 'postgres.sh'
START_TIMEOUT = 60.0
TABLES = ('drvs_vision_systems', 'drvs_ejections', 'drvs_watches')
"""The tables a test empties (:meth:`PostgresCluster.empty`): what the registry keeps."""


class PostgresCluster:
    """A cluster in a new folder under /tmp (readable by the cluster's own user); ``dsn`` once started.

    Use as a context manager: the cluster is stopped and its folder removed on exit.
    """

    def __init__(self) -> None:
        self.folder = tempfile.mkdtemp(prefix='drvs-pg-')
        self.dsn = ''

    def start(self) -> str:
        """Start (or start again) the cluster; its DSN (the same after a restart while its port is free)."""
        done = subprocess.run(
            ['bash', str(SCRIPT), 'start', self.folder],
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT,
        )
        if done.returncode != 0:
            raise RuntimeError(f'scripts/postgres.sh start failed ({done.returncode}): {done.stderr.strip()}')
        self.dsn = done.stdout.strip().splitlines()[-1]
        return self.dsn

    def empty(self) -> None:
        """Delete every registration, ejection and watch (tables not created yet are left alone)."""
        import psycopg  # only where PostgreSQL is installed (scripts/setup.sh --postgres)

        with psycopg.connect(self.dsn, autocommit=True) as connection:
            for table in TABLES:
                if connection.execute('SELECT to_regclass(%s)', (table,)).fetchone()[0]:
                    connection.execute(f'DELETE FROM {table}')

    def stop(self) -> None:
        subprocess.run(
            ['bash', str(SCRIPT), 'stop', self.folder], capture_output=True, text=True, timeout=START_TIMEOUT
        )

    def __enter__(self) -> PostgresCluster:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.stop()
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)


def shared_registry(store, clock, **settings):
    """An empty :class:`~drvs.server.shared_registry.SharedRegistry` on ``store`` (a
    :class:`~drvs.server.pg_store.PgStore` shared by a module's tests, emptied first), on ``clock``."""
    from drvs.server.shared_registry import SharedRegistry

    store.clock = clock
    store.clear()
    registry = SharedRegistry(store, clock=clock, **settings)
    registry.load()
    return registry
