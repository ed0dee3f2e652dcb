#!/usr/bin/env bash
# Scale-out numbers on 127.0.0.1 only, bounded in time and count (docs/gallery.md, "Several
# replicas on PostgreSQL"):
#
#   1. POST /verify with wrk: one replica on SQLite, then two replicas on one PostgreSQL database
#      behind nginx; same photos, same wrk settings; verifications/s, latency, server CPU.
#   2. Enrolment latency (p50/p95 of ENROLMENTS sequential POST /enroll of one IMM photo, each a new
#      subject) on each backend.
#   3. /identify over SUBJECTS synthetic subjects (examples/fill_gallery) on each backend: gallery
#      load time at start, identify latency with wrk, the replica's RSS.
#
#   scripts/loadtest-replicas.sh                 # 20 s per wrk run, 4 connections, 100,000 subjects
#   DURATION=10 SUBJECTS=10000 scripts/loadtest-replicas.sh
#
# PostgreSQL: a throwaway cluster (Debian's postgresql package: initdb + pg_ctl, as the postgres
# user when run as root, default durability settings) in a temporary directory, or DATABASE_URL
# (an empty database; it is filled). nginx (apt-get install nginx-light) runs in the foreground
# from a config in the temporary directory. Needs wrk, curl and the shared data (FACEGATE_SHARED).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

DURATION="${DURATION:-20}"
CONNECTIONS="${CONNECTIONS:-4}"
THREADS="${THREADS:-2}"
ENROLMENTS="${ENROLMENTS:-50}"
SUBJECTS="${SUBJECTS:-100000}"
SHARED="${FACEGATE_SHARED:-../shared}"
ENROL="${ENROL:-$SHARED/data/imm/01-1m.jpg}"
PROBE="${PROBE:-$SHARED/data/imm/01-2m.jpg}"
PORT="${PORT:-18180}"

for tool in wrk curl nginx python3; do
    command -v "$tool" >/dev/null || { echo "loadtest-replicas: $tool is missing" >&2; exit 1; }
done
for f in "$ENROL" "$PROBE"; do [[ -f "$f" ]] || { echo "loadtest-replicas: no photo $f" >&2; exit 1; }; done

BIN="${BIN:-}"
FILL="${FILL:-}"
if [[ -z "$BIN" || -z "$FILL" ]]; then
    cargo build --release --bin facegate --example fill_gallery
    BIN="${BIN:-target/release/facegate}"
    FILL="${FILL:-target/release/examples/fill_gallery}"
fi

tmp="$(mktemp -d)"
chmod 755 "$tmp"
pids=()
pg_ctl_stop=""
cleanup() {
    for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
    for pid in "${pids[@]}"; do wait "$pid" 2>/dev/null || true; done
    if [[ -n "$pg_ctl_stop" ]]; then eval "$pg_ctl_stop" >/dev/null 2>&1 || true; fi
    rm -rf "$tmp"
}
trap cleanup EXIT

# --- PostgreSQL -------------------------------------------------------------------------------
if [[ -n "${DATABASE_URL:-}" ]]; then
    PG_URL="$DATABASE_URL"
else
    pgbin="$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -1)"
    [[ -x "$pgbin/initdb" ]] || { echo "loadtest-replicas: no PostgreSQL server (apt-get install postgresql)" >&2; exit 1; }
    as_pg=()
    if [[ "$(id -u)" == 0 ]]; then as_pg=(runuser -u postgres --); mkdir -p "$tmp/pg"; chown postgres "$tmp/pg"; else mkdir -p "$tmp/pg"; fi
    pg_port=$((PORT + 50))
    "${as_pg[@]}" "$pgbin/initdb" -D "$tmp/pg/data" -A trust -U postgres -E UTF8 >/dev/null
    "${as_pg[@]}" "$pgbin/pg_ctl" -D "$tmp/pg/data" -l "$tmp/pg/log" -w \
        -o "-p $pg_port -k $tmp/pg -c listen_addresses=127.0.0.1 -c max_connections=200" start >/dev/null
    pg_ctl_stop="${as_pg[*]} $pgbin/pg_ctl -D $tmp/pg/data -m fast stop"
    "$pgbin/psql" "postgres://postgres@127.0.0.1:$pg_port/postgres" -qc "CREATE DATABASE facegate_load" >/dev/null
    PG_URL="postgres://postgres@127.0.0.1:$pg_port/facegate_load"
    echo "PostgreSQL $("$pgbin/postgres" --version | awk '{print $3}') on port $pg_port (fsync and synchronous_commit on)"
fi
pg_pid() { head -1 "$tmp/pg/data/postmaster.pid" 2>/dev/null || true; }

# --- helpers ----------------------------------------------------------------------------------
# start NAME PORT DATABASE: a replica, logging to $tmp/NAME.log; its pid in $last_pid.
start() {
    FACEGATE_API_KEYS="" RUST_LOG="warn,facegate::cli=info" "$BIN" serve --bind "127.0.0.1:$2" --database "$3" --queue 256 --console false --log-format json \
        >"$tmp/$1.log" 2>&1 &
    last_pid=$!
    pids+=("$last_pid")
}
wait_up() {
    for _ in $(seq 1 600); do
        curl -fsS "http://127.0.0.1:$1/health" >/dev/null 2>&1 && return 0
        sleep 0.2
    done
    echo "loadtest-replicas: nothing answers on port $1" >&2; tail -n 5 "$tmp"/*.log >&2; exit 1
}
stop() { kill "$1"; wait "$1" 2>/dev/null || true; }
cpu_ticks() { local t=0; for pid in "$@"; do t=$((t + $(awk '{print $14 + $15}' "/proc/$pid/stat"))); done; echo "$t"; }
rss_mb() { awk '/VmRSS/ {printf "%.0f", $2 / 1024}' "/proc/$1/status"; }
lua() { # lua PATH SUBJECT-or-empty: a wrk script posting the probe as multipart
    cat >"$tmp/post.lua" <<LUA
local f = assert(io.open("$PROBE", "rb"))
local photo = f:read("*a")
f:close()
local b = "facegateloadtestboundary"
wrk.method = "POST"
wrk.headers["Content-Type"] = "multipart/form-data; boundary=" .. b
local subject = "$2"
local body = ""
if subject ~= "" then
    body = "--" .. b .. "\r\nContent-Disposition: form-data; name=\"subject\"\r\n\r\n" .. subject .. "\r\n"
end
wrk.body = body .. "--" .. b .. "\r\nContent-Disposition: form-data; name=\"image\"; filename=\"probe.jpg\"\r\n"
    .. "Content-Type: image/jpeg\r\n\r\n" .. photo .. "\r\n--" .. b .. "--\r\n"
done = function(summary, latency, requests)
    local seconds = summary.duration / 1e6
    io.write(string.format("requests %d errors %d status-errors %d seconds %.1f\n", summary.requests,
        summary.errors.connect + summary.errors.read + summary.errors.write + summary.errors.timeout,
        summary.errors.status, seconds))
    io.write(string.format("p50 %.1f ms  p95 %.1f ms  p99 %.1f ms  throughput %.1f/s\n", latency:percentile(50) / 1e3,
        latency:percentile(95) / 1e3, latency:percentile(99) / 1e3, summary.requests / seconds))
end
LUA
}
# load LABEL URL PIDS...: a wrk run; prints its summary and the facegate CPU per request.
load() {
    local label="$1" url="$2"; shift 2
    local before; before="$(cpu_ticks "$@")"
    wrk -t "$THREADS" -c "$CONNECTIONS" -d "${DURATION}s" --timeout 10s -s "$tmp/post.lua" "$url" >"$tmp/wrk.txt"
    local after; after="$(cpu_ticks "$@")"
    local n; n="$(awk '/^requests/ {print $2}' "$tmp/wrk.txt")"
    echo "$label: $(tail -1 "$tmp/wrk.txt")  ($(awk '/^requests/ {print $2 " requests, " $4 " errors, " $6 " non-2xx"}' "$tmp/wrk.txt"))"
    python3 -c "import sys; t, hz, n = map(float, sys.argv[1:]); print(f'    facegate CPU {1e3 * t / hz / max(n, 1):.1f} ms per request')" \
        "$((after - before))" "$(getconf CLK_TCK)" "${n:-0}"
    awk '/throughput/ {print $NF}' "$tmp/wrk.txt" | tr -d '/s' >"$tmp/$label.rate"
}
# enrolments LABEL BASE: ENROLMENTS sequential enrolments, each of a new subject; p50/p95.
enrolments() {
    : >"$tmp/$1.enrol"
    for i in $(seq 1 "$ENROLMENTS"); do
        curl -fsS -o /dev/null -w '%{time_total}\n' -F "subject=enrol-$i" -F "image=@$ENROL" "$2/enroll" >>"$tmp/$1.enrol"
    done
    python3 -c "import sys,statistics as s; v=sorted(float(x)*1e3 for x in open(sys.argv[1])); q=s.quantiles(v,n=20); print(f'$1 enrolment: p50 {s.median(v):.1f} ms  p95 {q[18]:.1f} ms  ({len(v)} enrolments)')" "$tmp/$1.enrol"
}
loaded_ms() { grep -o '"load_ms":[0-9]*' "$tmp/$1.log" | tail -1 | cut -d: -f2; }
searched() { # searched BASE: the subjects an identification on BASE searched (its gallery's size)
    curl -fsS -F "image=@$PROBE" "$1/identify?k=1" | python3 -c 'import json,sys; print(json.load(sys.stdin)["subjects_searched"])'
}

echo "cores: $(nproc), load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
echo "wrk: ${DURATION}s, $CONNECTIONS connections, $THREADS threads, probe $(basename "$PROBE"), enrolled $(basename "$ENROL")"

# --- 1 and 2: SQLite, one replica -------------------------------------------------------------
start sqlite "$PORT" "sqlite://$tmp/load.db"; sq=$last_pid; wait_up "$PORT"
curl -fsS -F subject=loadtest -F "image=@$ENROL" "http://127.0.0.1:$PORT/enroll" >/dev/null
lua /verify loadtest
load sqlite-verify "http://127.0.0.1:$PORT/verify" "$sq"
enrolments sqlite "http://127.0.0.1:$PORT"

# --- 1 and 2: PostgreSQL, two replicas behind nginx ------------------------------------------
start pg-a "$((PORT + 1))" "$PG_URL"; pa=$last_pid
start pg-b "$((PORT + 2))" "$PG_URL"; pb=$last_pid
wait_up "$((PORT + 1))"; wait_up "$((PORT + 2))"
mkdir -p "$tmp/nginx"
cat >"$tmp/nginx/nginx.conf" <<NGINX
worker_processes 1;
pid $tmp/nginx/nginx.pid;
error_log $tmp/nginx/error.log;
events { worker_connections 256; }
http {
    access_log off;
    client_body_temp_path $tmp/nginx/body;
    proxy_temp_path $tmp/nginx/proxy;
    upstream facegate {
        server 127.0.0.1:$((PORT + 1));
        server 127.0.0.1:$((PORT + 2));
        keepalive 16;
    }
    server {
        listen 127.0.0.1:$((PORT + 3));
        client_max_body_size 17m;
        location / {
            proxy_pass http://facegate;
            proxy_http_version 1.1;
            proxy_set_header Connection "";
        }
    }
}
NGINX
nginx -c "$tmp/nginx/nginx.conf" -p "$tmp/nginx" -g 'daemon off;' &
pids+=("$!")
lb="http://127.0.0.1:$((PORT + 3))"
wait_up "$((PORT + 3))"
curl -fsS -F subject=loadtest -F "image=@$ENROL" "$lb/enroll" >/dev/null
load pg-verify "$lb/verify" "$pa" "$pb"
python3 -c "import sys; a, b = (float(open(p).read()) for p in sys.argv[1:]); print(f'two replicas on PostgreSQL behind nginx / one on SQLite: {b / a:.2f}x verifications/s')" \
    "$tmp/sqlite-verify.rate" "$tmp/pg-verify.rate"
enrolments postgres "http://127.0.0.1:$((PORT + 1))"

# --- 3: /identify over SUBJECTS synthetic subjects -------------------------------------------
lua /identify ""
echo "filling both stores with $SUBJECTS synthetic subjects (the replicas keep running: they follow the fill)"
"$FILL" "$PG_URL" loadtest "$SUBJECTS" 16 | sed 's/^/    postgres fill: /'
stop "$sq"
"$FILL" "sqlite://$tmp/load.db" loadtest "$SUBJECTS" 16 | sed 's/^/    sqlite fill: /'
echo "    replicas A and B followed the fill: their galleries hold $(searched "http://127.0.0.1:$((PORT + 1))") and $(searched "http://127.0.0.1:$((PORT + 2))") subjects; RSS A $(rss_mb "$pa") MB, B $(rss_mb "$pb") MB"
stop "$pa"; stop "$pb"
for backend in sqlite postgres; do
    if [[ $backend == sqlite ]]; then url="sqlite://$tmp/load.db"; else url="$PG_URL"; fi
    start "identify-$backend" "$((PORT + 4))" "$url"; ip=$last_pid; wait_up "$((PORT + 4))"
    echo "$backend, one replica: gallery of $(searched "http://127.0.0.1:$((PORT + 4))") subjects loaded at start in $(loaded_ms "identify-$backend") ms, RSS $(rss_mb "$ip") MB"
    load "$backend-identify" "http://127.0.0.1:$((PORT + 4))/identify?k=5" "$ip"
    stop "$ip"
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
