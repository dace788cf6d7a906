#!/usr/bin/env bash
# A scratch PostgreSQL server on loopback for the fleet store's tests and for trying the store
# out (not for production: trust authentication, no TLS).
#
#   scratch-postgres.sh start DIR PORT   creates the cluster in DIR when new, starts it on
#                                        127.0.0.1:PORT and prints its connection string
#   scratch-postgres.sh stop DIR         stops it (fast shutdown)
#
# PostgreSQL refuses to run as root: as root the server runs as the `postgres` user, which
# Debian's package creates (deploy/install-build-deps.sh installs it).
set -euo pipefail
cmd=${1:?start|stop}
dir=${2:?data directory}
initdb=$(ls /usr/lib/postgresql/*/bin/initdb 2>/dev/null | sort -V | tail -1 || true)
[ -n "$initdb" ] || { echo "no PostgreSQL server: run deploy/install-build-deps.sh" >&2; exit 1; }
bin=$(dirname "$initdb")
as_owner() {
  if [ "$(id -u)" -eq 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi
}
case "$cmd" in
  start)
    port=${3:?port}
    mkdir -p "$dir"
    [ "$(id -u)" -eq 0 ] && chown postgres "$dir"
    if [ ! -f "$dir/data/PG_VERSION" ]; then
      as_owner "$bin/initdb" -D "$dir/data" -U nori --auth=trust -E UTF8 --no-instructions >"$dir/initdb.log"
    fi
    as_owner "$bin/pg_ctl" -D "$dir/data" -l "$dir/server.log" -w -t 30 \
      -o "-h 127.0.0.1 -p $port -k $dir -c fsync=on -c max_connections=50" start >/dev/null
    "$bin/psql" -h 127.0.0.1 -p "$port" -U nori -d postgres -tAc \
      "SELECT 1 FROM pg_database WHERE datname = 'fleet'" | grep -q 1 \
      || "$bin/createdb" -h 127.0.0.1 -p "$port" -U nori fleet
    echo "host=127.0.0.1 port=$port user=nori dbname=fleet"
    ;;
  stop)
    as_owner "$bin/pg_ctl" -D "$dir/data" -m fast -w stop >/dev/null
    ;;
  *) echo "usage: $0 start DIR PORT | stop DIR" >&2; exit 2 ;;
esac
