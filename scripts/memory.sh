#!/usr/bin/env bash
# Resident memory of `facegate serve`: the peak while it loads its models (VmHWM when /health first
# answers), the idle resident size after that (VmRSS, 5 s later), and the peak after 30 s of
# POST /verify at 200 connections (VmHWM). Release build, fresh SQLite database, one IMM photo
# enrolled, another verified. Prints one line per figure and one JSON line.
#
#   scripts/memory.sh                                    # target/release/facegate
#   BIN=/tmp/old/facegate scripts/memory.sh              # another build
#   CONNECTIONS=200 DURATION=30 scripts/memory.sh
#
# Needs hey (apt-get install hey), curl and the shared data at ../shared (FACEGATE_SHARED).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

DURATION="${DURATION:-30}"
CONNECTIONS="${CONNECTIONS:-200}"
PORT="${PORT:-18090}"
SHARED="${FACEGATE_SHARED:-../shared}"
ENROL="${ENROL:-$SHARED/data/imm/01-1m.jpg}"
PROBE="${PROBE:-$SHARED/data/imm/01-2m.jpg}"
BIN="${BIN:-target/release/facegate}"

command -v hey >/dev/null || { echo "memory: hey is missing (apt-get install hey)" >&2; exit 1; }
[[ -x "$BIN" ]] || { echo "memory: no binary $BIN (cargo build --release --bin facegate)" >&2; exit 1; }
# shellcheck source=scripts/lib/scratch-server.sh
source scripts/lib/scratch-server.sh
status_mb() { awk -v key="$1:" '$1 == key { printf "%.1f", $2 / 1024 }' "/proc/$server_pid/status"; }

scratch_server "$BIN" "$PORT"
startup_peak="$(status_mb VmHWM)"
curl -fsS -F subject=memory -F "image=@$ENROL" "$base/enroll" >/dev/null
sleep 5
idle="$(status_mb VmRSS)"

# The probe as a multipart body for hey.
boundary="facegate-memory-boundary"
{
    printf -- '--%s\r\nContent-Disposition: form-data; name="subject"\r\n\r\nmemory\r\n' "$boundary"
    printf -- '--%s\r\nContent-Disposition: form-data; name="image"; filename="probe.jpg"\r\nContent-Type: image/jpeg\r\n\r\n' "$boundary"
    cat "$PROBE"
    printf -- '\r\n--%s--\r\n' "$boundary"
} >"$tmp/body"
hey -z "${DURATION}s" -c "$CONNECTIONS" -m POST -T "multipart/form-data; boundary=$boundary" -D "$tmp/body" \
    "$base/verify" >"$tmp/hey.txt"
load_peak="$(status_mb VmHWM)"
after="$(status_mb VmRSS)"
answered="$(grep -E "^\s*\[[0-9]+\]\s+[0-9]+ responses" "$tmp/hey.txt" | tr -s " " | paste -sd ";" -)"

echo "start-up peak (VmHWM when /health first answers): $startup_peak MB"
echo "idle (VmRSS 5 s after one enrolment):              $idle MB"
echo "peak after ${DURATION} s of /verify at $CONNECTIONS connections (VmHWM): $load_peak MB (VmRSS then $after MB)"
echo "answers: $answered"
printf '{"startup_vmhwm_mb":%s,"idle_vmrss_mb":%s,"load_vmhwm_mb":%s,"load_vmrss_mb":%s,"connections":%s,"seconds":%s}\n' \
    "$startup_peak" "$idle" "$load_peak" "$after" "$CONNECTIONS" "$DURATION"
