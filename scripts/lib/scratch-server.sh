# Sourced by scripts/loadtest.sh, scripts/memory.sh and scripts/challenge-cpu.sh: `facegate serve`
# on a fresh SQLite database in a temporary folder ($tmp), stopped and the folder removed when the
# script exits.
#
#   scratch_server BIN PORT [serve flags...]
#
# starts it, sets server_pid and base (http://127.0.0.1:PORT) and returns once /health answers;
# a server that exits or does not answer within 60 s ends the script with its log.
#   release_bin          sets BIN to the release build (built first) unless BIN is given.
#   server_cpu_ticks     the server's user + system time so far, in clock ticks.
tmp="$(mktemp -d)"
server_pid=""
cleanup() {
    if [[ -n "$server_pid" ]]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
    rm -rf "$tmp"
}
trap cleanup EXIT

scratch_server() {
    local bin="$1" port="$2"
    shift 2
    "$bin" serve --bind "127.0.0.1:$port" --database "sqlite://$tmp/facegate.db" "$@" >"$tmp/server.log" 2>&1 &
    server_pid=$!
    base="http://127.0.0.1:$port"
    for _ in $(seq 1 120); do
        curl -fsS "$base/health" >/dev/null 2>&1 && return 0
        kill -0 "$server_pid" 2>/dev/null || break
        sleep 0.5
    done
    echo "$(basename "$0"): the server did not come up" >&2
    cat "$tmp/server.log" >&2
    exit 1
}

release_bin() {
    if [[ -z "${BIN:-}" ]]; then
        cargo build --release --bin facegate
        BIN=target/release/facegate
    fi
}

# Fields 14 and 15 of /proc/<pid>/stat: user and system time in clock ticks (the command name in
# field 2 has no spaces here).
server_cpu_ticks() { awk '{print $14 + $15}' "/proc/$server_pid/stat"; }
