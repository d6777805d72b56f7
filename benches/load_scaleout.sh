#!/usr/bin/env bash
# The scale-out load run of BENCHMARKS.md ("Scale-out"): benches/load_trips.py against
#   (1) one server on the embedded store, (2) 2 replicas and (3) 3 replicas on one PostgreSQL
# database (a throw-away server in a temporary folder, 127.0.0.1 only, run as `postgres`).
# Bounded: 64 vehicles x BATCHES batches of 10 frames, at most MAX_SECONDS per run.
# usage: benches/load_scaleout.sh target/release/seasonloc ../shared/data/nordland_64x32 [BATCHES] [MAX_SECONDS]
# Prints one JSON line per configuration, each with the replicas' peak RSS (VmHWM, kB).
set -euo pipefail
bin=$(realpath "$1"); data=$(realpath "$2"); batches=${3:-8}; max=${4:-240}
python=${PYTHON:-python3}
here=$(dirname "$(realpath "$0")")
pgbin=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -1)
tmp=$(mktemp -d); chmod 755 "$tmp"
pids=()
as_pg() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; }
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  as_pg "$pgbin/pg_ctl" -D "$tmp/pg" -m fast -w stop >/dev/null 2>&1 || true
  rm -rf "$tmp"
}
trap cleanup EXIT
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
mkdir "$tmp/pg"; [ "$(id -u)" = 0 ] && chown postgres: "$tmp/pg"
as_pg "$pgbin/initdb" -D "$tmp/pg" -A trust -U postgres >/dev/null
pgport=$(free_port)
as_pg "$pgbin/pg_ctl" -D "$tmp/pg" -l "$tmp/pg/log" -w \
  -o "-p $pgport -k $tmp/pg -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null

# Starts one replica and sets URL (no command substitution: a subshell would lose its pid,
# leaving the replica running and unmeasured through the next configurations).
start() { # name, extra args...
  local name=$1; shift
  local port; port=$(free_port)
  "$bin" serve --addr "127.0.0.1:$port" "$@" >"$tmp/$name.log" 2>&1 &
  pids+=($!)
  for _ in $(seq 300); do
    if python3 -c "import urllib.request,sys; urllib.request.urlopen('http://127.0.0.1:$port/readyz', timeout=1)" 2>/dev/null; then
      URL="http://127.0.0.1:$port"; return
    fi
    sleep 0.1
  done
  echo "replica $name did not start: $(tail -3 "$tmp/$name.log")" >&2; exit 1
}
rss() { for p in "${pids[@]}"; do grep VmHWM "/proc/$p/status" | awk '{print $2}'; done | paste -sd, -; }
stop_all() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null; wait "$p" 2>/dev/null || true; done; pids=(); }

echo "# uptime: $(uptime)"
start single --data-dir "$tmp/single"; url=$URL
out=$("$python" "$here/load_trips.py" "$url" "$data" --batches "$batches" --max-seconds "$max")
echo "{\"config\":\"embedded\",\"rss_kb\":\"$(rss)\",\"result\":$out}"
stop_all
for n in 2 3; do
  db="load$n"
  as_pg "$pgbin/createdb" -h 127.0.0.1 -p "$pgport" -U postgres "$db"
  dburl="postgres://postgres@127.0.0.1:$pgport/$db"
  urls=()
  for k in $(seq "$n"); do start "r$n-$k" --database-url "$dburl"; urls+=("$URL"); done
  psql="$pgbin/psql -h 127.0.0.1 -p $pgport -U postgres -d $db"
  out=$("$python" "$here/load_trips.py" "$(IFS=,; echo "${urls[*]}")" "$data" --batches "$batches" --max-seconds "$max" --psql "$psql")
  echo "{\"config\":\"postgres x$n\",\"rss_kb\":\"$(rss)\",\"result\":$out}"
  stop_all
done
echo "# uptime: $(uptime)"
