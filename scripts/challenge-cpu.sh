#!/usr/bin/env bash
# Server CPU of a head-turn challenge against plain /verify calls of the same photos, in one run
# on one server.
#
# Starts `facegate serve --liveness enforce` on a fresh temporary database and enrols IMM person
# 15's view 1. The probe is view 2; a challenge's front steps are answered by view 5, its left
# steps by view 4 and its right ones by view 3 (turned faces cost more to landmark than frontal
# ones), each step a burst of BURST frames sent with `frame_steps`. Each of ROUNDS rounds runs
# PLAIN plain verifications of each of those four photos, then one verification answering a
# freshly drawn challenge; the server process's user + system time (/proc/<pid>/stat) is read
# around each batch, so every kind is timed alternately under the same conditions. Prints the CPU
# of a plain verification of each photo, of a challenged one, and the challenge against what its
# photos cost as plain verifications (the probe's and each frame's: what a challenge costs when
# answering it adds nothing to the analyses).
#
#   scripts/challenge-cpu.sh                          # release build, 10 rounds, bursts of 5
#   BURST=1 ROUNDS=20 scripts/challenge-cpu.sh        # one frame a step
#   BIN=target/debug/facegate scripts/challenge-cpu.sh
#
# Needs curl, python3 and the shared data at ../shared (FACEGATE_SHARED).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

ROUNDS="${ROUNDS:-10}"
PLAIN="${PLAIN:-5}"
BURST="${BURST:-5}"
PORT="${PORT:-18081}"
SHARED="${FACEGATE_SHARED:-../shared}"
imm="$SHARED/data/imm"
photo() { ls "$imm/15-$1"?.jpg | head -1; }
enrol="$(photo 1)" probe="$(photo 2)" front="$(photo 5)" left="$(photo 4)" right="$(photo 3)"

# shellcheck source=scripts/lib/scratch-server.sh
source scripts/lib/scratch-server.sh
release_bin
FACEGATE_API_KEYS="" RUST_LOG=warn scratch_server "$BIN" "$PORT" --liveness enforce --challenge-rate 0

curl -fsS -F subject=p15 -F "image=@$enrol" "$base/enroll" >/dev/null

declare -A ticks=([probe]=0 [front]=0 [left]=0 [right]=0 [challenge]=0) sent=([front]=0 [left]=0 [right]=0)
declare -A photo_of=([probe]="$probe" [front]="$front" [left]="$left" [right]="$right")
plain_n=0 challenge_n=0 passed=0
for _ in $(seq 1 "$ROUNDS"); do
    for kind in probe front left right; do
        before="$(server_cpu_ticks)"
        for _ in $(seq 1 "$PLAIN"); do
            curl -fsS -F subject=p15 -F "image=@${photo_of[$kind]}" "$base/verify" >/dev/null
        done
        ticks[$kind]=$((ticks[$kind] + $(server_cpu_ticks) - before))
    done
    plain_n=$((plain_n + PLAIN))

    # Draw a challenge (its id and steps), and build the form: each step's burst, in order.
    challenge="$(curl -fsS -X POST "$base/liveness/challenge")"
    mapfile -t form < <(python3 - "$challenge" "$BURST" "$front" "$left" "$right" <<'PY'
import json, sys
challenge, burst = json.loads(sys.argv[1]), int(sys.argv[2])
photo = {"front": sys.argv[3], "left": sys.argv[4], "right": sys.argv[5]}
print(f"challenge={challenge['challenge']}")
steps = []
for k, step in enumerate(challenge["steps"]):
    for _ in range(burst):
        print(f"frame=@{photo[step['turn']]}")
        steps.append(str(k))
print("frame_steps=" + ",".join(steps))
PY
)
    args=()
    for field in "${form[@]}"; do
        args+=(-F "$field")
        for kind in front left right; do
            [[ "$field" == "frame=@${photo_of[$kind]}" ]] && sent[$kind]=$((sent[$kind] + 1))
        done
    done
    before="$(server_cpu_ticks)"
    response="$(curl -sS -F subject=p15 -F "image=@$probe" "${args[@]}" "$base/verify")"
    ticks[challenge]=$((ticks[challenge] + $(server_cpu_ticks) - before)) challenge_n=$((challenge_n + 1))
    if python3 -c 'import json,sys; sys.exit(0 if json.loads(sys.argv[1]).get("liveness", {}).get("challenge", {}).get("passed") else 1)' "$response"; then
        passed=$((passed + 1))
    fi
done

python3 - "$(getconf CLK_TCK)" "$plain_n" "$challenge_n" "$passed" "$BURST" \
    "${ticks[probe]}" "${ticks[front]}" "${ticks[left]}" "${ticks[right]}" "${ticks[challenge]}" \
    "${sent[front]}" "${sent[left]}" "${sent[right]}" <<'PY'
import sys
hz, plain_n, chal_n, passed, burst = map(float, sys.argv[1:6])
probe, front, left, right, chal = (1e3 * float(t) / hz for t in sys.argv[6:11])
probe, front, left, right = (t / plain_n for t in (probe, front, left, right))
chal /= chal_n
sent = {k: float(n) / chal_n for k, n in zip(("front", "left", "right"), sys.argv[11:14])}
frames = sum(sent.values())
expected = probe + sent["front"] * front + sent["left"] * left + sent["right"] * right
print(f"plain /verify, server CPU ({int(plain_n)} each): probe {probe:.1f} ms, front {front:.1f} ms, left {left:.1f} ms, right {right:.1f} ms")
print(f"challenged /verify, bursts of {int(burst)}: {chal:.1f} ms ({int(chal_n)} challenges, {frames:.2f} frames each, {int(passed)} passed)")
print(f"its photos as plain verifications: {expected:.1f} ms; the challenge costs {chal / expected:.3f} times that ({chal / probe:.2f} probe verifications; frames + 1 = {frames + 1:.2f})")
PY
