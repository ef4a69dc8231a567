"""Sites (docs/registry.md, "Sites"): who is at another site, what a forward there carries, a name
held at another site, and two servers of two sites on one PostgreSQL registry (no ROS)."""

import doctest

import psycopg
import pytest
from psycopg import conninfo
from test_shared_registry import Client

import drvs.server.sites
from drvs.common.status import INVALID, UNAVAILABLE, Refusal
from drvs.server.pg_store import SCHEMA_VERSION, PgStore
from drvs.server.registration import Registrar
from drvs.server.shared_registry import SharedRegistry
from drvs.server.sites import callback_uri, direct_uri, remote, requested_callback_uri, site_name
from drvs.testing import ManualClock
from drvs.testing.postgres import shared_registry


def square(x, y, size=1.0):
    return [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]


def test_doctests():
    assert doctest.testmod(drvs.server.sites).failed == 0


@pytest.mark.parametrize(
    'ours, theirs, expected',
    [('', '', False), ('a', 'a', False), ('a', 'b', True), ('', 'b', True), ('a', '', True)],
)
def test_an_entry_is_remote_exactly_when_its_site_is_not_ours(ours, theirs, expected):
    assert remote(ours, theirs) is expected
    assert direct_uri(ours, theirs, 'rosrpc://h:1') == ('rosrpc://h:1' if expected else None)
    assert callback_uri(ours, theirs, 'rosrpc://robot:2') == ('rosrpc://robot:2' if expected else '')


@pytest.mark.parametrize('site', ['', 'a', 'hall-B_2', 'x' * 64])
def test_valid_site_names(site):
    assert site_name(site) == site


@pytest.mark.parametrize('site', ['hall b', 'a/b', 'x' * 65, 'é'])
def test_invalid_site_names_are_refused(site):
    with pytest.raises(ValueError, match='^must be letters, digits, _ or -, at most 64 of them, got '):
        site_name(site)


def test_a_caller_may_not_choose_the_callback_uri():
    requested_callback_uri('')
    with pytest.raises(Refusal) as caught:
        requested_callback_uri('rosrpc://elsewhere:1')
    assert caught.value.status == INVALID
    assert str(caught.value) == (
        "callback_uri: 'rosrpc://elsewhere:1'; leave it empty in a call to the DRVS server "
        '(it fills it for vision systems at other sites)'
    )


@pytest.fixture
def clock():
    return ManualClock(1000.0)


@pytest.fixture
def two_sites(dsn, clock):
    """Server A (site a) and server B (site b) on one emptied database, sharing ``clock``."""
    stores = [PgStore(dsn, site='a'), PgStore(dsn, site='b')]
    for store in stores:
        store.open()
    a = shared_registry(stores[0], clock, lease=10.0, site='a', make_client=Client)
    stores[1].clock = clock
    b = SharedRegistry(stores[1], lease=10.0, clock=clock, site='b', make_client=Client)
    b.load()
    yield a, b
    for store in stores:
        store.close()


def test_an_entry_of_the_other_site_is_called_at_its_address(two_sites):
    a, b = two_sites
    assert b.register('/vs1', square(0, 0), provider='/vs1', instance='rosrpc://cam-b:41000') == 'registered'
    assert b.get('/vs1').site == 'b' and b.get('/vs1').client is None  # registered there: no client asked
    a.sync()
    entry = a.get('/vs1')
    assert (entry.site, entry.instance) == ('b', 'rosrpc://cam-b:41000')
    assert (entry.client.name, entry.client.uri) == ('/vs1', 'rosrpc://cam-b:41000')
    assert a.match((0.2, 0.2, 0.4, 0.4)) == ['/vs1']
    # Restarted at site B on another port: server A calls the new address through a new client.
    b.register('/vs1', [], provider='/vs1')
    b.register('/vs1', square(0, 0), provider='/vs1', instance='rosrpc://cam-b:42000')
    a.sync()
    assert a.get('/vs1').client.uri == 'rosrpc://cam-b:42000'
    [retired] = a.take_retired()
    assert retired.uri == 'rosrpc://cam-b:41000' and a.take_retired() == []


def test_an_entry_of_our_site_is_looked_up_on_our_master(two_sites, dsn, clock):
    a, _ = two_sites
    a.register('/vs2', square(0, 0), provider='/vs2', instance='rosrpc://cam-a:1')
    replica = PgStore(dsn, clock=clock, site='a')
    replica.open()
    try:
        other = SharedRegistry(replica, clock=clock, site='a', make_client=Client)
        other.load()
        assert other.get('/vs2').client.uri is None
    finally:
        replica.close()


def test_a_name_registered_at_another_site_is_refused_until_its_lease_ends(two_sites, clock):
    a, b = two_sites
    b.register('/vs1', square(0, 0), provider='/vs1', instance='rosrpc://cam-b:41000')
    a.sync()
    clock.now += 4
    with pytest.raises(Refusal) as caught:
        a.register('/vs1', square(5, 5), provider='/vs1', instance='rosrpc://cam-a:1')
    assert (caught.value.status, caught.value.retry_after) == (UNAVAILABLE, 6.0)
    assert str(caught.value) == (
        'service_name: /vs1 is registered at site b for 6.0 s more; vision systems at different sites '
        'need different names (give each a namespace of its own)'
    )
    assert a.match((0.2, 0.2, 0.4, 0.4)) == ['/vs1'] and a.get('/vs1').site == 'b'


def test_only_a_server_of_its_site_unregisters_an_entry(two_sites):
    a, b = two_sites
    b.register('/vs1/detect', square(0, 0), provider='/vs1', instance='rosrpc://cam-b:41000')
    a.sync()
    registrar = Registrar(a, '/drvs', None, Client, lambda *_: None, lambda _: None)
    with pytest.raises(Refusal) as caught:
        registrar.register('/vs1/detect', [], [], '/vs1')
    assert caught.value.status == INVALID
    assert str(caught.value) == (
        'service_name: /vs1/detect is registered at site b; only a server of that site may unregister it'
    )
    assert '/vs1/detect' in a


def test_each_site_keeps_and_takes_over_only_its_own_watches(two_sites, dsn):
    from drvs.server.shared_registry import StoredWatch

    a, b = two_sites
    for registry in (a, b):  # a robot of the same name at each site, with the same request id
        registry.store.save_watch(
            StoredWatch('/robot', 'w', 'colour', 'colour', (0, 0, 1, 1), '/robot/cb', 0.5, 20.0, False, 20.0)
        )
    with psycopg.connect(dsn) as connection:
        rows = connection.execute('SELECT site FROM drvs_watches ORDER BY site').fetchall()
    assert rows == [('a',), ('b',)]
    a.store.clock.now += 10  # both replicas silent for 10 s; a third replica of site a looks
    third = PgStore(dsn, clock=a.store.clock, site='a')
    third.open()
    try:
        taken = third.orphaned_watches(stale_after=5.0)
    finally:
        third.close()
    assert [(w.caller, w.request_id) for w in taken] == [('/robot', 'w')]
    with psycopg.connect(dsn) as connection:
        owners = dict(connection.execute('SELECT site, owner FROM drvs_watches').fetchall())
    assert owners['a'] == third.replica and owners['b'] == b.store.replica


def test_a_version_1_database_is_upgraded_in_place(dsn):
    """The schema of version 1 (no sites): its rows stay, at the site ''."""
    parts = conninfo.conninfo_to_dict(dsn)
    with psycopg.connect(dsn, autocommit=True) as admin:
        admin.execute('DROP DATABASE IF EXISTS drvs_upgrade')
        admin.execute('CREATE DATABASE drvs_upgrade')
    old = conninfo.make_conninfo(**{**parts, 'dbname': 'drvs_upgrade'})
    try:
        store = PgStore(old)
        store.open()  # a new database: version 2 ...
        store.close()
        with psycopg.connect(old, autocommit=True) as connection:  # ... taken back to version 1
            connection.execute('ALTER TABLE drvs_vision_systems DROP COLUMN site')
            connection.execute(
                'ALTER TABLE drvs_watches DROP CONSTRAINT drvs_watches_pkey, DROP COLUMN site, '
                'ADD PRIMARY KEY (caller, request_id)'
            )
            connection.execute('UPDATE drvs_schema SET version = 1')
            connection.execute(
                """INSERT INTO drvs_vision_systems (service_name, field_of_view, outline, algorithms,
                       provider, instance, watch_service, expires_at, replica)
                   VALUES ('/old', ST_GeomFromText('POLYGON((0 0,1 0,1 1,0 0))'), '{0,0,1,0,1,1}', '{}',
                       '/vs', 'rosrpc://h:1', false, extract(epoch from clock_timestamp()) + 60, 'r1')"""
            )
        store = PgStore(old, site='a')
        store.open()
        try:
            _, entries = store.snapshot()
        finally:
            store.close()
        assert [(e.service_name, e.site, e.instance) for e in entries] == [('/old', '', 'rosrpc://h:1')]
        with psycopg.connect(old) as connection:
            assert connection.execute('SELECT version FROM drvs_schema').fetchall() == [(SCHEMA_VERSION,)]
            key = connection.execute(
                "SELECT pg_get_constraintdef(oid) FROM pg_constraint WHERE conname = 'drvs_watches_pkey'"
            ).fetchone()[0]
        assert key == 'PRIMARY KEY (site, caller, request_id)'
    finally:
        with psycopg.connect(dsn, autocommit=True) as admin:
            admin.execute('DROP DATABASE IF EXISTS drvs_upgrade WITH (FORCE)')


def test_forwards_that_fail_across_sites_never_remove_the_entry(two_sites):
    a, b = two_sites
    b.register('/vs1', square(0, 0), provider='/vs1', instance='rosrpc://cam-b:41000')
    a.sync()
    for _ in range(5):
        assert a.record_failure('/vs1') is None
    assert a.failures('/vs1') == 5 and a.match((0.2, 0.2, 0.4, 0.4)) == ['/vs1']
    b.sync()
    assert b.ejected_until('/vs1') is None and '/vs1' in b
