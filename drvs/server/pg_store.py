"""The registry's store in PostgreSQL with PostGIS: the schema, and every statement it runs.

:class:`PgStore` implements :class:`~drvs.server.shared_registry.RegistryStore` over one
psycopg 3 connection (autocommit, one statement or transaction at a time). Every value reaches
SQL as a bound parameter; no statement is built from input. Times are seconds since the epoch by
the database's clock (or an injected one, for tests), so replicas on several hosts agree. A lost
connection raises :class:`~drvs.server.shared_registry.StoreUnavailable` and the next call
connects again. The schema and why it is so: docs/registry.md.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import psycopg
from psycopg import conninfo
from shapely.geometry import Polygon

from drvs.server.shared_registry import (
    Change,
    StoredEjection,
    StoredEntry,
    StoredWatch,
    StoreError,
    StoreUnavailable,
)
from drvs.server.spatial_index import _box_geometry

__all__ = ['SCHEMA_VERSION', 'UPGRADES', 'PgStore', 'describe_dsn']

logger = logging.getLogger('rosout.' + __name__)

T = TypeVar('T')

SCHEMA_VERSION = 2
"""The schema this code reads and writes (table ``drvs_schema``); an older one is upgraded
(:data:`UPGRADES`), a newer one refused."""
CHANGES_KEPT = 600.0
"""Seconds the change log keeps a line; a replica cut off longer reads a whole snapshot."""
RENEW_BATCH = 500
"""Leases renewed per statement."""
CONNECT_TIMEOUT = 3
"""Seconds to connect before the database counts as out of reach."""
STATEMENT_TIMEOUT_MS = 5000
"""A statement running longer is cancelled (the database is as good as out of reach)."""
LOG_LOCK = 0x44525653_0001
"""Transaction advisory lock that orders writes of the change log (so a sequence number is never
committed after a larger one that a replica already read)."""
SWEEP_LOCK = 0x44525653_0002
"""Session advisory lock held by the one replica that sweeps."""
SETUP_LOCK = 0x44525653_0003
"""Transaction advisory lock around creating the schema (two replicas starting at once)."""

NOW = 'coalesce(%(now)s::float8, extract(epoch from clock_timestamp()))'

SCHEMA = [
    'CREATE EXTENSION IF NOT EXISTS postgis',
    'CREATE TABLE drvs_schema (version integer NOT NULL)',
    # fillfactor 70: a renewal's new row version fits on its page, so the update is HOT (no index
    # touched) — possible only because no index covers expires_at (docs/registry.md).
    """CREATE TABLE drvs_vision_systems (
        service_name text PRIMARY KEY,
        field_of_view geometry(Polygon) NOT NULL,
        outline float8[] NOT NULL,
        algorithms text[] NOT NULL,
        provider text NOT NULL,
        instance text NOT NULL,
        watch_service boolean NOT NULL,
        expires_at float8 NOT NULL,
        replica text NOT NULL,
        site text NOT NULL DEFAULT ''
    ) WITH (fillfactor = 70)""",
    'CREATE INDEX drvs_vision_systems_field_of_view ON drvs_vision_systems USING gist (field_of_view)',
    """CREATE TABLE drvs_changes (
        seq bigserial PRIMARY KEY,
        service_name text NOT NULL,
        at float8 NOT NULL
    )""",
    """CREATE TABLE drvs_ejections (
        service_name text PRIMARY KEY,
        times integer NOT NULL,
        refused_until float8 NOT NULL,
        instance text NOT NULL
    )""",
    # A watch's texts come from callers as they are (a request_id may hold any character, NUL too,
    # which PostgreSQL's text cannot): kept as their UTF-8 bytes.
    """CREATE TABLE drvs_watches (
        caller bytea NOT NULL,
        request_id bytea NOT NULL,
        owner text NOT NULL,
        algorithm bytea NOT NULL,
        algorithm_name bytea NOT NULL,
        region float8[] NOT NULL,
        callback_service bytea NOT NULL,
        period float8 NOT NULL,
        duration float8 NOT NULL,
        changes_only boolean NOT NULL,
        expires_at float8 NOT NULL,
        forward_callback bytea,
        forward_request_id bytea,
        site text NOT NULL DEFAULT '',
        PRIMARY KEY (site, caller, request_id)
    )""",
    'CREATE TABLE drvs_replicas (replica text PRIMARY KEY, seen float8 NOT NULL)',
]
UPGRADES = {
    # 1 -> 2: each entry's site (docs/registry.md, "Sites"); the rows of a version-1 database were
    # all registered at the one site there was, ''. Adding a column with a constant default
    # rewrites nothing (PostgreSQL 11 and later).
    # A watch is its site's: a robot's name means something on its own master only.
    1: [
        "ALTER TABLE drvs_vision_systems ADD COLUMN site text NOT NULL DEFAULT ''",
        "ALTER TABLE drvs_watches ADD COLUMN site text NOT NULL DEFAULT ''",
        'ALTER TABLE drvs_watches DROP CONSTRAINT drvs_watches_pkey, '
        'ADD PRIMARY KEY (site, caller, request_id)',
    ],
}
"""The statements that take a database from version N to N + 1, run under the schema lock."""
ENTRY_COLUMNS = (
    'outline, algorithms, provider, instance, watch_service, expires_at - ' + NOW + ', replica, site'
)


def describe_dsn(dsn: str) -> str:
    """``dsn`` without its password, for messages: ``postgresql://user@host:port/dbname``."""
    try:
        parts = conninfo.conninfo_to_dict(dsn)
    except psycopg.Error:
        return '(an unreadable DSN)'
    user = parts.get('user', '')
    where = f'{parts.get("host", "localhost")}:{parts.get("port", 5432)}'
    return f'postgresql://{user + "@" if user else ""}{where}/{parts.get("dbname", "")}'


def _first_line(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = lines[0] if lines else type(error).__name__
    return text.removeprefix('connection failed: ').replace('FATAL:  ', '')


class PgStore:
    """The shared registry in PostgreSQL (see the module's docstring).

    :param dsn: a ``postgresql://`` connection string.
    :param clock: seconds since the epoch; default: the database's clock.
    :param replica: this server's name among the replicas (default: a new random one).
    :param site: this server's site: the watches it saves are that site's, and it takes over only
        those (:mod:`drvs.server.sites`).
    """

    def __init__(self, dsn: str, clock: Callable[[], float] | None = None, replica: str = '', site: str = ''):
        self.dsn = dsn
        self.site = site
        self.where = describe_dsn(dsn)
        self.clock = clock
        self.replica = replica or uuid.uuid4().hex[:12]
        self._lock = threading.Lock()
        self._connection: psycopg.Connection | None = None
        self._sweeper = False

    # -- connection ----------------------------------------------------------------------------
    def open(self) -> None:
        """Connect and check (or create) the schema.

        :raises StoreError: the DSN, the password or the schema is wrong; the database did not answer.
        """
        try:
            conninfo.conninfo_to_dict(self.dsn)
        except psycopg.Error as error:
            raise StoreError(f'~registry: not a valid PostgreSQL DSN ({_first_line(error)})') from None
        try:
            with self._lock:
                self._connect()
        except StoreUnavailable as error:
            raise StoreError(f'~registry: cannot use the registry database {self.where}: {error}') from None

    def _connect(self) -> psycopg.Connection:
        if self._connection is not None and not self._connection.closed:
            return self._connection
        self._sweeper = False
        try:
            connection = psycopg.connect(
                self.dsn,
                autocommit=True,
                connect_timeout=CONNECT_TIMEOUT,
                options=f'-c statement_timeout={STATEMENT_TIMEOUT_MS}',
                keepalives=1,
                keepalives_idle=5,
                keepalives_interval=2,
                keepalives_count=2,
                application_name=f'drvs_server {self.replica}',
            )
        except psycopg.Error as error:
            raise StoreUnavailable(_first_line(error)) from None
        try:
            self._check_schema(connection)
        except psycopg.Error as error:
            connection.close()
            raise StoreUnavailable(_first_line(error)) from None
        except StoreError:
            connection.close()
            raise
        self._connection = connection
        return connection

    def _check_schema(self, connection: psycopg.Connection) -> None:
        with connection.transaction():
            connection.execute('SELECT pg_advisory_xact_lock(%s)', (SETUP_LOCK,))
            exists = connection.execute("SELECT to_regclass('drvs_schema') IS NOT NULL").fetchone()[0]  # type: ignore[index]
            if not exists:
                others = connection.execute(
                    'SELECT count(*) FROM pg_tables WHERE schemaname = current_schema() '
                    "AND tablename LIKE 'drvs%%'"
                ).fetchone()[0]  # type: ignore[index]
                if others:
                    raise StoreError(
                        f'~registry: the database {self.where} has drvs tables but no drvs_schema table: '
                        'not a DRVS registry this server can use (use another database, or drop them)'
                    )
                for statement in SCHEMA:
                    connection.execute(statement)
                connection.execute('INSERT INTO drvs_schema (version) VALUES (%s)', (SCHEMA_VERSION,))
                return
            versions = [row[0] for row in connection.execute('SELECT version FROM drvs_schema')]
            if len(versions) == 1 and versions[0] in UPGRADES:
                self._upgrade(connection, versions[0])
                return
            if versions != [SCHEMA_VERSION]:
                raise StoreError(
                    f'~registry: the database {self.where} holds DRVS schema version '
                    f'{", ".join(map(str, versions)) or "(none)"}; this drvs_server knows versions '
                    f'up to {SCHEMA_VERSION}: run a drvs_server of that version, or give it a new database'
                )

    def _upgrade(self, connection: psycopg.Connection, version: int) -> None:
        """Take the schema from ``version`` to :data:`SCHEMA_VERSION` (in the caller's transaction,
        under the schema lock: one replica upgrades, the others find it done)."""
        while version < SCHEMA_VERSION:
            for statement in UPGRADES[version]:
                connection.execute(statement)
            version += 1
        connection.execute('UPDATE drvs_schema SET version = %s', (SCHEMA_VERSION,))
        logger.warning(
            'registry: upgraded the database %s to DRVS schema version %d', self.where, SCHEMA_VERSION
        )

    def close(self) -> None:
        with self._lock:
            if self._connection is not None:
                self._connection.close()
                self._connection = None

    def _now(self) -> float | None:
        return self.clock() if self.clock is not None else None

    def _run(self, work: Callable[[psycopg.Connection], T]) -> T:
        """``work(connection)`` under the store's lock; a lost connection is :class:`StoreUnavailable`."""
        with self._lock:
            connection = self._connect()
            try:
                return work(connection)
            except (psycopg.OperationalError, psycopg.InterfaceError) as error:
                connection.close()
                self._connection = None
                raise StoreUnavailable(_first_line(error)) from None

    # -- entries -------------------------------------------------------------------------------
    def snapshot(self) -> tuple[int, list[StoredEntry]]:
        def work(connection):
            with connection.transaction():
                # A million rows take longer than the statement limit: no limit for this one read,
                # streamed through a server-side cursor.
                connection.execute('SET TRANSACTION ISOLATION LEVEL REPEATABLE READ')
                connection.execute('SET LOCAL statement_timeout = 0')
                position = connection.execute('SELECT coalesce(max(seq), 0) FROM drvs_changes').fetchone()[0]  # type: ignore[index]
                with connection.cursor(name='drvs_snapshot') as cursor:
                    cursor.itersize = 10_000
                    cursor.execute(
                        f'SELECT service_name, {ENTRY_COLUMNS} FROM drvs_vision_systems', {'now': self._now()}
                    )
                    entries = [_entry(row[0], row[1:]) for row in cursor]
            return position, entries

        return self._run(work)

    def changes(self, after: int) -> list[Change] | None:
        def work(connection):
            with connection.transaction():
                oldest = connection.execute('SELECT min(seq) FROM drvs_changes').fetchone()[0]  # type: ignore[index]
                if oldest is not None and oldest > after + 1:
                    return None
                rows = connection.execute(
                    f"""SELECT c.seq, c.service_name, v.service_name IS NOT NULL, {ENTRY_COLUMNS}
                        FROM drvs_changes c LEFT JOIN drvs_vision_systems v USING (service_name)
                        WHERE c.seq > %(after)s ORDER BY c.seq LIMIT 10000""",
                    {'now': self._now(), 'after': after},
                ).fetchall()
            return [Change(row[0], row[1], _entry(row[1], row[3:]) if row[2] else None) for row in rows]

        return self._run(work)

    def write(self, entry: StoredEntry, lease: float) -> None:
        outline = [value for point in entry.field_of_view for value in point]
        values = {
            'name': entry.service_name,
            'shape': Polygon(entry.field_of_view).wkb,
            'outline': outline,
            'algorithms': list(entry.algorithms),
            'provider': entry.provider,
            'instance': entry.instance,
            'watch_service': entry.watch_service,
            'lease': lease,
            'replica': entry.replica or self.replica,
            'site': entry.site,
            'now': self._now(),
        }

        def work(connection):
            with connection.transaction():
                connection.execute('SET LOCAL synchronous_commit = off')
                connection.execute('SELECT pg_advisory_xact_lock(%s)', (LOG_LOCK,))
                connection.execute(
                    f"""INSERT INTO drvs_vision_systems (service_name, field_of_view, outline, algorithms,
                            provider, instance, watch_service, expires_at, replica, site)
                        VALUES (%(name)s, ST_GeomFromWKB(%(shape)s), %(outline)s, %(algorithms)s,
                            %(provider)s, %(instance)s, %(watch_service)s, {NOW} + %(lease)s, %(replica)s,
                            %(site)s)
                        ON CONFLICT (service_name) DO UPDATE SET field_of_view = excluded.field_of_view,
                            outline = excluded.outline, algorithms = excluded.algorithms,
                            provider = excluded.provider, instance = excluded.instance,
                            watch_service = excluded.watch_service, expires_at = excluded.expires_at,
                            replica = excluded.replica, site = excluded.site""",
                    values,
                )
                self._log(connection, [entry.service_name])

        self._run(work)

    def _log(self, connection: psycopg.Connection, names: Sequence[str]) -> None:
        connection.execute(
            f'INSERT INTO drvs_changes (service_name, at) SELECT unnest(%(names)s::text[]), {NOW}',
            {'names': list(names), 'now': self._now()},
        )

    def delete(self, service_name: str) -> None:
        def work(connection):
            with connection.transaction():
                connection.execute('SELECT pg_advisory_xact_lock(%s)', (LOG_LOCK,))
                gone = connection.execute(
                    'DELETE FROM drvs_vision_systems WHERE service_name = %s', (service_name,)
                ).rowcount
                if gone:
                    self._log(connection, [service_name])

        self._run(work)

    def renew(self, renewals: Sequence[tuple[str, float]], lease: float) -> list[str]:
        def work(connection):
            found: set[str] = set()
            for start in range(0, len(renewals), RENEW_BATCH):
                batch = renewals[start : start + RENEW_BATCH]
                with connection.transaction():
                    connection.execute('SET LOCAL synchronous_commit = off')
                    rows = connection.execute(
                        f"""UPDATE drvs_vision_systems v SET expires_at = {NOW} + %(lease)s - r.ago
                            FROM unnest(%(names)s::text[], %(ages)s::float8[]) AS r(name, ago)
                            WHERE v.service_name = r.name RETURNING v.service_name""",
                        {
                            'names': [name for name, _ in batch],
                            'ages': [age for _, age in batch],
                            'lease': lease,
                            'now': self._now(),
                        },
                    ).fetchall()
                found.update(row[0] for row in rows)
            return [name for name, _ in renewals if name not in found]

        return self._run(work)

    def match(self, region: Sequence[float], algorithm: str | None = None) -> list[str]:
        """The live vision systems whose field of view's interior meets ``region`` (the registry's
        rule, answered by PostGIS under its GiST index): for tests and the benchmark."""
        values = {'region': _box_geometry(region).wkb, 'algorithm': algorithm, 'now': self._now()}

        def work(connection):
            rows = connection.execute(
                f"""SELECT service_name FROM drvs_vision_systems
                    WHERE field_of_view && ST_GeomFromWKB(%(region)s)
                      AND ST_Relate(field_of_view, ST_GeomFromWKB(%(region)s), 'T********')
                      AND expires_at > {NOW}
                      AND (%(algorithm)s::text IS NULL OR %(algorithm)s::text = ANY(algorithms))
                    ORDER BY service_name""",
                values,
            ).fetchall()
            return [row[0] for row in rows]

        return self._run(work)

    # -- ejections -----------------------------------------------------------------------------
    def ejection(self, service_name: str) -> StoredEjection | None:
        def work(connection):
            return connection.execute(
                f"""SELECT times, refused_until - {NOW}, instance FROM drvs_ejections
                    WHERE service_name = %(name)s AND refused_until > {NOW}""",
                {'name': service_name, 'now': self._now()},
            ).fetchone()

        row = self._run(work)
        return None if row is None else StoredEjection(row[0], row[1], row[2])

    def eject(
        self, service_name: str, instance: str, ejection_time: float, max_ejection_time: float
    ) -> StoredEjection:
        values = {
            'name': service_name,
            'instance': instance,
            'time': ejection_time,
            'most': max_ejection_time,
            'now': self._now(),
        }

        def work(connection):
            return connection.execute(
                f"""INSERT INTO drvs_ejections AS e (service_name, times, refused_until, instance)
                    VALUES (%(name)s, 1, {NOW} + least(%(time)s, %(most)s), %(instance)s)
                    ON CONFLICT (service_name) DO UPDATE SET times = e.times + 1,
                        refused_until = {NOW} + least(%(time)s * (e.times + 1), %(most)s),
                        instance = excluded.instance
                    RETURNING times, refused_until - {NOW}, instance""",
                values,
            ).fetchone()

        row = self._run(work)
        return StoredEjection(row[0], row[1], row[2])

    def forgive(self, service_name: str) -> None:
        self._run(lambda c: c.execute('DELETE FROM drvs_ejections WHERE service_name = %s', (service_name,)))

    # -- the sweeper ---------------------------------------------------------------------------
    def sweep(self, max_ejection_time: float) -> bool:
        values = {'now': self._now(), 'most': max_ejection_time, 'kept': CHANGES_KEPT}

        def work(connection):
            if not self._sweeper:
                self._sweeper = connection.execute(
                    'SELECT pg_try_advisory_lock(%s)', (SWEEP_LOCK,)
                ).fetchone()[0]  # type: ignore[index]
                if not self._sweeper:
                    return False
            with connection.transaction():
                connection.execute('SELECT pg_advisory_xact_lock(%s)', (LOG_LOCK,))
                connection.execute(
                    f"""WITH gone AS (DELETE FROM drvs_vision_systems WHERE expires_at <= {NOW}
                                      RETURNING service_name)
                        INSERT INTO drvs_changes (service_name, at) SELECT service_name, {NOW} FROM gone""",
                    values,
                )
                connection.execute(
                    f"""DELETE FROM drvs_changes WHERE at < {NOW} - %(kept)s
                        AND seq < (SELECT max(seq) FROM drvs_changes)""",
                    values,
                )
                connection.execute(
                    f'DELETE FROM drvs_ejections WHERE refused_until + %(most)s < {NOW}', values
                )
                connection.execute(f'DELETE FROM drvs_watches WHERE expires_at <= {NOW}', values)
            return True

        return self._run(work)

    def heartbeat(self) -> None:
        self._run(
            lambda c: c.execute(
                f"""INSERT INTO drvs_replicas (replica, seen) VALUES (%(replica)s, {NOW})
                    ON CONFLICT (replica) DO UPDATE SET seen = excluded.seen""",
                {'replica': self.replica, 'now': self._now()},
            )
        )

    # -- watches -------------------------------------------------------------------------------
    def save_watch(self, watch: StoredWatch) -> None:
        forward = watch.forward_as or (None, None)
        values = {
            'caller': _bytes(watch.caller),
            'request_id': _bytes(watch.request_id),
            'owner': self.replica,
            'algorithm': _bytes(watch.algorithm),
            'algorithm_name': _bytes(watch.algorithm_name),
            'region': list(watch.region),
            'callback': _bytes(watch.callback_service),
            'period': watch.period,
            'duration': watch.duration,
            'changes_only': watch.changes_only,
            'left': watch.left,
            'forward_callback': _bytes(forward[0]),
            'forward_request_id': _bytes(forward[1]),
            'site': self.site,
            'now': self._now(),
        }
        self._run(
            lambda c: c.execute(
                f"""INSERT INTO drvs_watches (caller, request_id, owner, algorithm, algorithm_name, region,
                        callback_service, period, duration, changes_only, expires_at, forward_callback,
                        forward_request_id, site)
                    VALUES (%(caller)s, %(request_id)s, %(owner)s, %(algorithm)s, %(algorithm_name)s,
                        %(region)s, %(callback)s, %(period)s, %(duration)s, %(changes_only)s,
                        {NOW} + %(left)s, %(forward_callback)s, %(forward_request_id)s, %(site)s)
                    ON CONFLICT (site, caller, request_id) DO UPDATE SET owner = excluded.owner,
                        algorithm = excluded.algorithm, algorithm_name = excluded.algorithm_name,
                        region = excluded.region, callback_service = excluded.callback_service,
                        period = excluded.period, duration = excluded.duration,
                        changes_only = excluded.changes_only, expires_at = excluded.expires_at,
                        forward_callback = excluded.forward_callback,
                        forward_request_id = excluded.forward_request_id""",
                values,
            )
        )

    def drop_watch(self, caller: str, request_id: str) -> None:
        self._run(
            lambda c: c.execute(
                'DELETE FROM drvs_watches WHERE site = %s AND caller = %s AND request_id = %s AND owner = %s',
                (self.site, _bytes(caller), _bytes(request_id), self.replica),
            )
        )

    def orphaned_watches(self, stale_after: float) -> list[StoredWatch]:
        values = {'replica': self.replica, 'site': self.site, 'stale': stale_after, 'now': self._now()}

        def work(connection):
            return connection.execute(
                f"""UPDATE drvs_watches SET owner = %(replica)s
                    WHERE site = %(site)s AND expires_at > {NOW} AND owner <> %(replica)s AND owner NOT IN
                        (SELECT replica FROM drvs_replicas WHERE seen > {NOW} - %(stale)s)
                    RETURNING caller, request_id, algorithm, algorithm_name, region, callback_service,
                        period, duration, changes_only, expires_at - {NOW}, forward_callback,
                        forward_request_id""",
                values,
            ).fetchall()

        rows = self._run(work)
        return [
            StoredWatch(
                _text(row[0]),
                _text(row[1]),
                _text(row[2]),
                _text(row[3]),
                (row[4][0], row[4][1], row[4][2], row[4][3]),
                _text(row[5]),
                row[6],
                row[7],
                row[8],
                row[9],
                (_text(row[10]), _text(row[11])) if row[10] is not None else None,
            )
            for row in rows
        ]

    def clear(self) -> None:
        """Remove every row (tests share one database between their registries)."""

        def work(connection):
            with connection.transaction():
                connection.execute('SELECT pg_advisory_xact_lock(%s)', (LOG_LOCK,))
                for table in ('drvs_vision_systems', 'drvs_ejections', 'drvs_watches', 'drvs_replicas'):
                    connection.execute(f'DELETE FROM {table}')  # noqa: S608 (a constant table name)

        self._run(work)


def _entry(name: str, row: Sequence[Any]) -> StoredEntry:
    outline, algorithms, provider, instance, watch_service, left, replica, site = row
    points = tuple(zip(outline[0::2], outline[1::2], strict=True))
    return StoredEntry(
        name, points, tuple(algorithms), provider, instance, watch_service, left, replica, site
    )


def _bytes(text: str | None) -> bytes | None:
    return None if text is None else text.encode('utf-8', 'surrogatepass')


def _text(data: bytes) -> str:
    return bytes(data).decode('utf-8', 'surrogatepass')
