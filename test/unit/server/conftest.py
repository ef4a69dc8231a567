"""The registry's backends for the contract tests: each test that takes ``new_registry`` runs
against the in-memory registry and against PostgreSQL (one cluster per module; docs/registry.md)."""

import pytest

from drvs.server.pg_store import PgStore
from drvs.server.registry import Registry
from drvs.testing.postgres import shared_registry

BACKENDS = ('memory', 'postgresql')


@pytest.fixture(scope='module')
def dsn(postgres):
    """The DSN of the module's cluster."""
    return postgres.dsn


@pytest.fixture(scope='module')
def pg_store(postgres):
    """One store (one connection) on the module's cluster; each test empties it."""
    store = PgStore(postgres.dsn)
    store.open()
    yield store
    store.close()


@pytest.fixture(params=BACKENDS)
def new_registry(request):
    """``new_registry(clock=..., **settings)``: an empty registry of the test's backend."""
    if request.param == 'memory':
        return Registry
    store = request.getfixturevalue('pg_store')

    def make(clock, **settings):
        return shared_registry(store, clock, **settings)

    return make
