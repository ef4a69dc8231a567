#!/usr/bin/env bash
# A private PostgreSQL + PostGIS cluster for DRVS's registry (docs/registry.md).
#
#   scripts/postgres.sh start DIR   create (first time) and start a cluster in DIR on a free port of
#                                   127.0.0.1 (again: the same port if it is free); its DSN is the
#                                   last line on stdout
#   scripts/postgres.sh stop DIR    stop it (the files stay; start again, or rm -rf DIR)
#   scripts/postgres.sh dsn DIR     print the DSN of a started cluster
#
# Never the system's cluster, never a fixed port. PostgreSQL refuses to run as root: as root, the
# cluster runs as the system user drvs-pg (created if missing) and DIR is handed to it. The database
# `drvs` gets the PostGIS extension; drvs_server creates its tables on first start. Needs
# `scripts/setup.sh --postgres` (Debian's postgresql-15 and postgresql-15-postgis-3).
set -euo pipefail

say() { printf 'postgres.sh: %s\n' "$*" >&2; }
die() { printf 'postgres.sh: error: %s\n' "$*" >&2; exit 2; }

[ $# -eq 2 ] || die "usage: $0 start|stop|dsn DIR"
action=$1
dir=$2
PG_USER=drvs-pg
bin=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)
[ -n "$bin" ] && [ -x "$bin/pg_ctl" ] || die "PostgreSQL is not installed: run scripts/setup.sh --postgres"

as_owner() {  # run "$@" as the cluster's owner
  if [ "$(id -u)" -eq 0 ]; then
    runuser -u "$PG_USER" -- "$@"
  else
    "$@"
  fi
}

dsn_of() {
  local port password
  port=$(cat "$dir/port")
  password=$(cat "$dir/password")
  printf 'postgresql://drvs:%s@127.0.0.1:%s/drvs\n' "$password" "$port"
}

free_port() {
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

case "$action" in
  start)
    mkdir -p "$dir"
    dir=$(cd "$dir" && pwd)
    if [ "$(id -u)" -eq 0 ]; then
      id -u "$PG_USER" >/dev/null 2>&1 \
        || useradd --system --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin "$PG_USER"
      chown "$PG_USER" "$dir"
      chmod 700 "$dir"
      runuser -u "$PG_USER" -- test -w "$dir" \
        || die "$dir: the user $PG_USER cannot reach it (a parent folder is closed to others); use a folder under /tmp"
    fi
    if [ ! -f "$dir/data/PG_VERSION" ]; then
      say "creating a cluster in $dir/data"
      umask 077
      python3 -c 'import secrets; print(secrets.token_hex(16))' > "$dir/password"
      [ "$(id -u)" -ne 0 ] || chown "$PG_USER" "$dir/password"
      as_owner "$bin/initdb" -D "$dir/data" -U drvs --pwfile="$dir/password" --auth-local=scram-sha-256 \
        --auth-host=scram-sha-256 -E UTF8 --locale=C.UTF-8 >"$dir/initdb.log" 2>&1 \
        || die "initdb failed: $(tail -3 "$dir/initdb.log")"
      {
        echo "listen_addresses = '127.0.0.1'"
        echo "unix_socket_directories = '$dir'"
        echo 'fsync = on'
        echo 'synchronous_commit = on'
        echo 'max_connections = 100'
        echo 'shared_buffers = 128MB'
      } | as_owner tee -a "$dir/data/postgresql.conf" >/dev/null
    fi
    if as_owner "$bin/pg_ctl" -D "$dir/data" status >/dev/null 2>&1; then
      dsn_of
      exit 0
    fi
    started=no
    # The port of the last start if it is still free (a restart keeps its DSN), else a free one; a free
    # port may be taken between the check and the start: then another.
    previous=$(cat "$dir/port" 2>/dev/null || true)
    for _ in 1 2 3 4 5; do
      port=${previous:-$(free_port)}
      previous=
      if as_owner "$bin/pg_ctl" -D "$dir/data" -l "$dir/server.log" -w -t 30 -o "-p $port" start >/dev/null; then
        echo "$port" > "$dir/port"
        started=yes
        break
      fi
    done
    [ "$started" = yes ] || die "the cluster would not start: $(tail -3 "$dir/server.log")"
    export PGPASSWORD
    PGPASSWORD=$(cat "$dir/password")
    psql=("$bin/psql" -h 127.0.0.1 -p "$port" -U drvs -v ON_ERROR_STOP=1 -q)
    if [ "$("${psql[@]}" -d postgres -Atc "SELECT 1 FROM pg_database WHERE datname = 'drvs'")" != 1 ]; then
      "${psql[@]}" -d postgres -c 'CREATE DATABASE drvs' >/dev/null
      "${psql[@]}" -d drvs -c 'CREATE EXTENSION IF NOT EXISTS postgis' >/dev/null \
        || die "CREATE EXTENSION postgis failed: run scripts/setup.sh --postgres (postgresql-15-postgis-3)"
    fi
    say "started on 127.0.0.1:$port (stop: $0 stop $dir)"
    dsn_of
    ;;
  stop)
    [ -d "$dir/data" ] || die "$dir: no cluster here"
    if as_owner "$bin/pg_ctl" -D "$dir/data" status >/dev/null 2>&1; then
      as_owner "$bin/pg_ctl" -D "$dir/data" -m fast -w -t 30 stop >/dev/null
      say "stopped the cluster in $dir"
    fi
    ;;
  dsn)
    [ -f "$dir/port" ] || die "$dir: no cluster started here"
    dsn_of
    ;;
  *) die "unknown action $action (start, stop or dsn)" ;;
esac
