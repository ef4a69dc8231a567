#!/usr/bin/env bash
# A private PostgreSQL + PostGIS cluster for DRVS's registry (docs/registry.md).
#
#   scripts/postgres.sh start DIR [--listen ADDRESS/PREFIX]
#                                   create (first time) and start a cluster in DIR on a free port of
#                                   127.0.0.1 (again: the same port if it is free); its DSN is the
#                                   last line on stdout. --listen: on ADDRESS too, password logins
#                                   from its network (e.g. 10.1.2.3/24), and the DSN names ADDRESS
#                                   (scripts/run_scenario.sh --sites: a database other hosts reach)
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

usage="usage: $0 start DIR [--listen ADDRESS/PREFIX] | stop DIR | dsn DIR"
[ $# -eq 2 ] || { [ $# -eq 4 ] && [ "$1" = start ] && [ "$3" = --listen ]; } || die "$usage"
action=$1
dir=$2
listen=${4:-}
network=""
if [ -n "$listen" ]; then
  # The address and its network, e.g. 10.1.2.3/24 -> 10.1.2.3 and 10.1.2.0/24.
  network=$(python3 -c 'import ipaddress, sys; print(ipaddress.ip_interface(sys.argv[1]).network)' "$listen" 2>/dev/null) \
    && [[ "$listen" =~ ^[0-9.]+/[0-9]+$ ]] || die "--listen needs an IPv4 ADDRESS/PREFIX, e.g. 10.1.2.3/24, got $listen"
  listen=${listen%/*}
fi
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
  local port password host
  port=$(cat "$dir/port")
  password=$(cat "$dir/password")
  host=$(cat "$dir/host" 2>/dev/null || echo 127.0.0.1)
  printf 'postgresql://drvs:%s@%s:%s/drvs\n' "$password" "$host" "$port"
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
      [ -z "$listen" ] || [ "$(cat "$dir/host" 2>/dev/null)" = "$listen" ] \
        || die "the cluster in $dir runs already, not listening on $listen: stop it first"
      dsn_of
      exit 0
    fi
    # --listen: the address and a password login from its network (pg_hba.conf, the line marked so
    # that the next start replaces it); without it, 127.0.0.1 only.
    as_owner sed -i '/# postgres.sh --listen$/d' "$dir/data/pg_hba.conf"
    addresses=127.0.0.1
    if [ -n "$listen" ]; then
      addresses=127.0.0.1,$listen
      echo "host all all $network scram-sha-256  # postgres.sh --listen" | as_owner tee -a "$dir/data/pg_hba.conf" >/dev/null
      echo "$listen" > "$dir/host"
    else
      rm -f "$dir/host"
    fi
    started=no
    # The port of the last start if it is still free (a restart keeps its DSN), else a free one; a free
    # port may be taken between the check and the start: then another.
    previous=$(cat "$dir/port" 2>/dev/null || true)
    for _ in 1 2 3 4 5; do
      port=${previous:-$(free_port)}
      previous=
      if as_owner "$bin/pg_ctl" -D "$dir/data" -l "$dir/server.log" -w -t 30 -o "-p $port -h $addresses" start >/dev/null; then
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
    say "started on ${listen:-127.0.0.1}:$port (stop: $0 stop $dir)"
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
