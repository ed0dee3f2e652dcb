#!/usr/bin/env bash
# Load test of POST /verify against the release build, on 127.0.0.1 only.
#
# Starts `facegate serve` on a fresh temporary database, enrols one IMM photo, then runs wrk with
# a multipart POST of a 640x480 IMM JPEG of the same person to /verify for a bounded time and
# prints p50/p99 latency, requests per second, the server's CPU time per verification (user +
# system time of the server process over the wrk run, from /proc/<pid>/stat: the number that does
# not depend on what else the machine is doing) and the load average.
#
#   scripts/loadtest.sh            # 30 s, 4 connections, 2 wrk threads
#   DURATION=60 CONNECTIONS=8 scripts/loadtest.sh
#   PROBE=../shared/data/imm/01-3m.jpg scripts/loadtest.sh     # a turned face (C-ASM + 3D-ASM)
#   BIN=/tmp/old/facegate FACEGATE_MODELS=/tmp/old/models scripts/loadtest.sh   # another build
#
# Needs wrk (apt-get install wrk) and the shared data at ../shared (FACEGATE_SHARED).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

DURATION="${DURATION:-30}"
CONNECTIONS="${CONNECTIONS:-4}"
THREADS="${THREADS:-2}"
PORT="${PORT:-18080}"
SHARED="${FACEGATE_SHARED:-../shared}"
ENROL="${ENROL:-$SHARED/data/imm/01-1m.jpg}"
PROBE="${PROBE:-$SHARED/data/imm/01-2m.jpg}"

command -v wrk >/dev/null || { echo "loadtest: wrk is missing (apt-get install wrk)" >&2; exit 1; }
command -v curl >/dev/null || { echo "loadtest: curl is missing" >&2; exit 1; }
for f in "$ENROL" "$PROBE"; do [[ -f "$f" ]] || { echo "loadtest: no photo $f" >&2; exit 1; }; done

# shellcheck source=scripts/lib/scratch-server.sh
source scripts/lib/scratch-server.sh
release_bin
FACEGATE_API_KEYS="" RUST_LOG=warn scratch_server "$BIN" "$PORT" --queue 256

curl -fsS -F subject=loadtest -F "image=@$ENROL" "$base/enroll" >/dev/null
echo "one verification, for reference:"
curl -fsS -F subject=loadtest -F "image=@$PROBE" "$base/verify" | python3 -c \
    'import json,sys; v=json.load(sys.stdin); print({k: v[k] for k in ("match","score","threshold","faces_found")}, v["timings"])'

cat >"$tmp/verify.lua" <<'LUA'
local f = assert(io.open(os.getenv("PROBE"), "rb"))
local photo = f:read("*a")
f:close()
local boundary = "facegateloadtestboundary"
wrk.method = "POST"
wrk.headers["Content-Type"] = "multipart/form-data; boundary=" .. boundary
wrk.body = "--" .. boundary .. "\r\n"
    .. "Content-Disposition: form-data; name=\"subject\"\r\n\r\nloadtest\r\n"
    .. "--" .. boundary .. "\r\n"
    .. "Content-Disposition: form-data; name=\"image\"; filename=\"probe.jpg\"\r\n"
    .. "Content-Type: image/jpeg\r\n\r\n" .. photo .. "\r\n"
    .. "--" .. boundary .. "--\r\n"

done = function(summary, latency, requests)
    local seconds = summary.duration / 1e6
    -- errors.status counts responses with status >= 400.
    io.write(string.format("requests: %d in %.1f s, errors: connect %d read %d write %d timeout %d status %d\n",
        summary.requests, seconds, summary.errors.connect, summary.errors.read, summary.errors.write,
        summary.errors.timeout, summary.errors.status))
    io.write(string.format("p50 %.1f ms  p90 %.1f ms  p99 %.1f ms  max %.1f ms\n",
        latency:percentile(50) / 1e3, latency:percentile(90) / 1e3, latency:percentile(99) / 1e3, latency.max / 1e3))
    io.write(string.format("throughput: %.1f verifications/s\n", summary.requests / seconds))
end
LUA

echo "wrk: ${DURATION}s, $CONNECTIONS connections, $THREADS threads, POST /verify with $(basename "$PROBE") ($(python3 -c "import sys,struct;d=open(sys.argv[1],'rb').read();print(len(d))" "$PROBE") bytes)"
echo "cores: $(nproc)"
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
ticks_before="$(server_cpu_ticks)"
PROBE="$PROBE" wrk -t "$THREADS" -c "$CONNECTIONS" -d "${DURATION}s" --timeout 10s -s "$tmp/verify.lua" "$base/verify" | tee "$tmp/wrk.txt"
ticks_after="$(server_cpu_ticks)"
requests="$(awk '/^requests:/ {print $2}' "$tmp/wrk.txt")"
python3 -c "import sys; t, hz, n = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]); print(f'server CPU: {t / hz:.2f} s for {n} verifications = {1e3 * t / hz / max(n, 1):.1f} ms per verification')" \
    "$((ticks_after - ticks_before))" "$(getconf CLK_TCK)" "${requests:-0}"
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
