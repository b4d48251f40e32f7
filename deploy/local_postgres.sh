#!/usr/bin/env bash
# A throwaway PostgreSQL cluster on 127.0.0.1 for the scale-out replicas (tests, local trials): Debian's
# postgresql-15 binaries, run as the postgres user (initdb refuses root), data under DIR.
#
#   deploy/local_postgres.sh start DIR [PORT]   # prints the libpq connection string for --postgres
#   deploy/local_postgres.sh stop DIR           # stops it and removes DIR
# In production the deployment runs its own PostgreSQL (deploy/k8s/overlays/scaleout).
set -euo pipefail
usage() { echo "usage: $0 start DIR [PORT] | stop DIR" >&2; exit 2; }
[ $# -ge 2 ] || usage
cmd=$1 dir=$2 port=${3:-}
pgbin=/usr/lib/postgresql/15/bin
[ -x "$pgbin/initdb" ] || { echo "local_postgres: $pgbin/initdb is missing: run deploy/install_deps.sh" >&2; exit 1; }
as_pg() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; }
case "$cmd" in
  start)
    mkdir -p "$dir"
    [ "$(id -u)" = 0 ] && chown postgres:postgres "$dir"
    if [ -z "$port" ]; then
      port=$(python3 -c 'import socket;s=socket.socket();s.bind(("127.0.0.1",0));print(s.getsockname()[1])')
    fi
    if [ ! -f "$dir/data/PG_VERSION" ]; then
      as_pg "$pgbin/initdb" -D "$dir/data" -U postgres -A trust -E UTF8 --locale=C.UTF-8 --no-sync >"$dir/initdb.log" 2>&1 ||
        { echo "local_postgres: initdb failed, see $dir/initdb.log" >&2; exit 1; }
    fi
    # fsync stays on: the tests check that what was acknowledged survives.
    as_pg "$pgbin/pg_ctl" -D "$dir/data" -l "$dir/postgres.log" -w -t 30 \
      -o "-p $port -k $dir -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null ||
      { echo "local_postgres: the server did not start, see $dir/postgres.log" >&2; exit 1; }
    echo "host=127.0.0.1 port=$port user=postgres dbname=postgres"
    ;;
  stop)
    if [ -f "$dir/data/postmaster.pid" ]; then as_pg "$pgbin/pg_ctl" -D "$dir/data" -m fast -w stop >/dev/null || true; fi
    rm -rf "$dir"
    ;;
  *) usage ;;
esac
