"""Registry backends: match, registration and renewal p50, in memory and in PostgreSQL, in one run.

For each size N (10k and 100k; 1M in the full size) and each backend, through the server's own
path (:meth:`~drvs.server.registry.Registry.register`, :meth:`~drvs.server.registry.Registry.match`):

- **memory**: a :class:`~drvs.server.registry.Registry` holding N cameras (the same random 2 x 1.5 m
  quadrilaterals as the ``registry`` section, 0.5 per square metre);
- **postgresql**: a :class:`~drvs.server.shared_registry.SharedRegistry` on a private cluster
  (scripts/postgres.sh, on this machine) holding N cameras: the rows are loaded in bulk (COPY)
  and the replica reads them at start, as a replica does; then

  - **match** (cache): the replica's in-process match, what a request pays;
  - **match** (PostGIS): the same regions asked of PostgreSQL under its GiST index through
    psycopg (``PgStore.match``), what a match would cost without the cache;
  - **registration**: new cameras registered one by one (one transaction each: the row, the
    change log line);
  - **renewal**: the call (kept in memory) and the batch that writes it: ``flush`` of 500
    renewals timed, per renewal;
  - **sweep**: one sweep with nothing expired, the sequential scan of every lease.

Run alone: ``.venv/bin/python -m bench.run --only registry_db`` (``--size quick``). How the
registry uses the database: docs/registry.md.
"""

from __future__ import annotations

import gc
import random
import time

from bench.common import Context, Section, spread, table
from bench.registry import DENSITY, camera, regions, timed

NAME = 'registry_db'
TITLE = 'Registry backends: memory and PostgreSQL, 10k to 1M fields of view'

NEW = 300  # cameras registered one by one on top of N, timed
MATCHES = 500  # regions matched, timed
RENEW_BATCH = 500  # renewals per flush


def run(ctx: Context) -> Section:
    from drvs.server.pg_store import PgStore
    from drvs.testing.postgres import PostgresCluster

    sizes = ctx.pick([1000], [10_000, 100_000], [10_000, 100_000, 1_000_000])
    measured = []
    with PostgresCluster() as cluster:
        store = PgStore(cluster.dsn, replica='bench')
        store.open()
        try:
            for n in sizes:
                rng = random.Random(28)
                side = (n / DENSITY) ** 0.5
                cameras = [camera(rng, side) for _ in range(n + NEW)]
                boxes = regions(rng, side, MATCHES)
                ctx.progress(f'memory, {n:,} cameras')
                memory = measure_memory(cameras, n, boxes)
                gc.collect()
                ctx.progress(f'postgresql, {n:,} cameras: bulk load')
                postgres = measure_postgres(ctx, store, cameras, n, boxes)
                measured.append({'n': n, 'memory': memory, 'postgresql': postgres})
                gc.collect()
        finally:
            store.close()
    return Section(NAME, TITLE, results={'sizes': measured}, markdown=report(measured))


def measure_memory(cameras, n: int, boxes) -> dict:
    from drvs.server.registry import Registry

    registry = Registry(lease=3600.0)
    for i in range(n):
        registry.register(f'/c{i}', cameras[i])
    names = [f'/c{i}' for i in range(n, n + NEW)]
    registration = timed(lambda i: registry.register(names[i], cameras[n + i]), range(NEW))
    renewal = timed(lambda i: registry.register(names[i], cameras[n + i]), range(NEW))
    match = timed(registry.match, boxes)
    return {'match_us': spread(match), 'register_us': spread(registration), 'renew_us': spread(renewal)}


def measure_postgres(ctx: Context, store, cameras, n: int, boxes) -> dict:
    from drvs.server.shared_registry import SharedRegistry

    started = time.perf_counter()
    bulk_load(store, cameras[:n])
    load_s = time.perf_counter() - started
    ctx.progress(f'postgresql, {n:,} cameras: a replica reads them')
    registry = SharedRegistry(store, lease=3600.0)
    started = time.perf_counter()
    registry.load()
    read_s = time.perf_counter() - started
    gc.collect()
    ctx.progress(f'postgresql, {n:,} cameras: match, register, renew')
    names = [f'/new{i}' for i in range(NEW)]
    registration = timed(lambda i: registry.register(names[i], cameras[n + i]), range(NEW))
    renewal = timed(lambda i: registry.register(names[i], cameras[n + i]), range(NEW))
    registry.flush()
    flushes = []
    all_names = [f'/c{i}' for i in range(n)]
    for _ in range(5):  # batches of renewals of cameras registered through this replica
        batch = random.sample(all_names, RENEW_BATCH)
        with registry._lock:
            registry._claimed.update(batch)
            registry._renewals.update((name, registry.clock()) for name in batch)
        flush_started = time.perf_counter_ns()
        registry.flush()
        flushes.append((time.perf_counter_ns() - flush_started) / 1e3 / RENEW_BATCH)
    sweeps = timed(lambda _: store.sweep(3600.0), range(5))  # nothing expired: the scan of every lease
    match = timed(registry.match, boxes)
    postgis = timed(store.match, boxes)
    agree = all(registry.match(box) == store.match(box) for box in boxes[:50])
    return {
        'match_us': spread(match),
        'postgis_match_us': spread(postgis),
        'register_us': spread(registration),
        'renew_call_us': spread(renewal),
        'renew_written_us': spread(flushes),
        'sweep_ms': round(spread(sweeps)['p50'] / 1e3, 1),
        'bulk_load_s': round(load_s, 1),
        'replica_read_s': round(read_s, 1),
        'agree': agree,
    }


def bulk_load(store, cameras) -> None:
    """``cameras`` as rows ``/c0`` ... in one COPY (what a registry of that size holds), replacing all."""
    from shapely.geometry import Polygon

    from drvs.server.pg_store import SCHEMA

    def work(connection):
        connection.execute('SET statement_timeout = 0')  # a million rows take longer than the server's limit
        with connection.transaction():  # the GiST index built once, after the rows (faster than row by row)
            connection.execute('TRUNCATE drvs_vision_systems, drvs_changes')
            connection.execute('DROP INDEX drvs_vision_systems_field_of_view')
            with connection.cursor().copy(
                'COPY drvs_vision_systems (service_name, field_of_view, outline, algorithms, provider, '
                'instance, watch_service, expires_at, replica) FROM STDIN'
            ) as copy:
                far = time.time() + 86400.0
                for i, points in enumerate(cameras):
                    outline = [value for point in points for value in point]
                    copy.write_row(
                        (f'/c{i}', Polygon(points).wkb_hex, outline, ['colour'], '', '', False, far, 'bench')
                    )
            connection.execute(
                next(statement for statement in SCHEMA if statement.startswith('CREATE INDEX'))
            )
        connection.execute('VACUUM ANALYZE drvs_vision_systems')
        connection.execute('RESET statement_timeout')

    store._run(work)


def report(measured: list[dict]) -> str:
    rows = []
    for entry in measured:
        memory, postgres = entry['memory'], entry['postgresql']
        rows.append(
            [
                f"{entry['n']:,}",
                memory['match_us']['p50'],
                postgres['match_us']['p50'],
                postgres['postgis_match_us']['p50'],
                memory['register_us']['p50'],
                postgres['register_us']['p50'],
                memory['renew_us']['p50'],
                postgres['renew_call_us']['p50'],
                postgres['renew_written_us']['p50'],
            ]
        )
    loads = ', '.join(
        f"{e['n']:,}: bulk load {e['postgresql']['bulk_load_s']} s, read by a replica "
        f"{e['postgresql']['replica_read_s']} s, one sweep {e['postgresql']['sweep_ms']} ms"
        for e in measured
    )
    agree = all(e['postgresql']['agree'] for e in measured)
    return (
        'p50 in µs of each call, both backends in one run on the same cameras and regions (3 x 3 m). '
        "With PostgreSQL a match is answered by the replica's in-memory cache; the PostGIS column is the "
        'same match asked of the database (GiST index, psycopg, localhost). A renewal is kept in memory '
        f"by the call and written in batches of {RENEW_BATCH} (the last column: one batch's time per "
        'renewal, synchronous_commit off).\n\n'
        + table(
            [
                'fields of view',
                'match memory',
                'match PostgreSQL (cache)',
                'match PostGIS',
                'register memory',
                'register PostgreSQL',
                'renew memory',
                'renew PostgreSQL (call)',
                'renew PostgreSQL (written)',
            ],
            rows,
        )
        + f"\n\nLoading the rows, and the sweeper's scan of every lease (no index on `expires_at`, "
        f'nothing expired: p50 of 5): {loads}. The cache and PostGIS gave the same answers: '
        + ('yes' if agree else '**no**')
        + '.\n'
    )
