#!/usr/bin/env bash
# facegate with curl and jq: enrol photos, verify a probe, verify with a head-turn challenge.
#
#   ./facegate_example.sh enroll alice alice-1.jpg alice-2.jpg
#   ./facegate_example.sh verify alice probe.jpg [FMR]        # e.g. 1e-4
#   ./facegate_example.sh verify-challenge alice probe.jpg --left l.jpg [--left l2.jpg] --right r.jpg [--front f.jpg]
#
# verify-challenge asks for a challenge (POST /liveness/challenge), answers each step with the
# photos given for its turn (`front` defaults to the probe; a real client takes a short burst of
# camera frames per step, well inside the step's yaw range) and verifies the probe with them. An
# option given more than once makes a burst: each step gets all its turn's photos (at most the
# challenge's `max_frames_per_step`), sent with `frame_steps`; with one photo per turn, one frame
# per step.
#
# FACEGATE_URL (default http://127.0.0.1:8080) and FACEGATE_API_KEY (if the server has keys) set the
# server. Exit status: 0 enrolled / match, 1 no match, 2 a photo is unusable (no face, a printed photo,
# a failed challenge, ...), 3 model mismatch (enrol the subject again), 4 any other error.
set -euo pipefail
url="${FACEGATE_URL:-http://127.0.0.1:8080}"
auth=()
[[ -n "${FACEGATE_API_KEY:-}" ]] && auth=(-H "Authorization: Bearer $FACEGATE_API_KEY")
body="$(mktemp)" headers="$(mktemp)"
trap 'rm -f "$body" "$headers"' EXIT

# post PATH CURL-ARGS...: POST multipart; retries `overloaded` (503) after Retry-After seconds.
# Leaves the response in $body and sets $status and $problem (the problem type's slug, or empty).
post() {
    local path="$1" attempt delay
    shift
    for attempt in 1 2 3 4 5; do
        status="$(curl -sS "${auth[@]}" -o "$body" -D "$headers" -w '%{http_code}' "$@" "$url$path")" || return 4
        problem=""
        if grep -qi '^content-type: application/problem+json' "$headers"; then
            problem="$(jq -r '.type | ltrimstr("https://facegate.dev/problems/")' "$body")"
        fi
        [[ "$problem" == overloaded && $attempt -lt 5 ]] || return 0
        delay="$(sed -n 's/^retry-after: *\([0-9]*\).*/\1/Ip' "$headers")"
        echo "facegate is busy; retrying in ${delay:-1} s" >&2
        sleep "${delay:-1}"
    done
}

# Map a problem to the exit status above.
refused() {
    if jq -e '.reason? | strings' "$body" >/dev/null 2>&1; then
        echo "the head-turn challenge failed: $(jq -r .reason "$body") ($problem)" >&2
        return 2
    fi
    case "$problem" in
        no-face | several-faces | presentation-attack | not-an-image | corrupt-image | unsupported-format | too-large)
            echo "$(jq -r 'if .frame then "frame \(.frame + 1)" else "photo \(.image // 0)" end' "$body") refused: $(jq -r .detail "$body") ($problem); take another photo" >&2
            return 2 ;;
        model-mismatch)
            echo "$subject was enrolled with another model version: enrol the subject again" >&2
            return 3 ;;
        *)
            echo "facegate refused (HTTP $status): $(jq -r '.detail // .' "$body" 2>/dev/null || cat "$body")" >&2
            return 4 ;;
    esac
}

command="${1:-}" subject="${2:-}"
case "$command" in
    enroll)
        [[ $# -ge 3 ]] || { echo "usage: $0 enroll SUBJECT PHOTO..." >&2; exit 4; }
        images=()
        for photo in "${@:3}"; do images+=(-F "image=@$photo"); done
        post /enroll -F "subject=$subject" "${images[@]}"
        [[ "$status" == 201 ]] || { refused; exit $?; }
        jq -r '"enrolled \(.subject): \(.added) template(s) added, \(.templates) in all"' "$body" ;;
    verify)
        [[ $# -ge 3 ]] || { echo "usage: $0 verify SUBJECT PHOTO [FMR]" >&2; exit 4; }
        post "/verify${4:+?fmr=$4}" -F "subject=$subject" -F "image=@$3"
        [[ "$status" == 200 ]] || { refused; exit $?; }
        jq -r '"\(if .match then "match" else "no match" end): score \(.score), threshold \(.threshold) at FMR \(.fmr)"' "$body"
        jq -e .match "$body" >/dev/null || exit 1 ;;
    verify-challenge)
        [[ $# -ge 3 ]] || { echo "usage: $0 verify-challenge SUBJECT PROBE --left PHOTO... --right PHOTO... [--front PHOTO...]" >&2; exit 4; }
        # Each option may be given more than once: the photos of its turn's burst.
        probe="$3" front=() left=() right=()
        shift 3
        while [[ $# -gt 0 ]]; do
            case "$1" in
                --front) front+=("$2") ;;
                --left) left+=("$2") ;;
                --right) right+=("$2") ;;
                *) echo "unknown option $1" >&2; exit 4 ;;
            esac
            shift 2
        done
        [[ ${#left[@]} -gt 0 && ${#right[@]} -gt 0 ]] || { echo "verify-challenge needs --left and --right" >&2; exit 4; }
        [[ ${#front[@]} -gt 0 ]] || front=("$probe")
        post /liveness/challenge -X POST
        [[ "$status" == 201 ]] || { refused; exit $?; }
        challenge="$(jq -r .challenge "$body")" most="$(jq -r '.max_frames_per_step // 5' "$body")"
        jq -r '"challenge of \(.steps | length) steps: \([.steps[] | "\(.turn) (\(.yaw_min)..\(.yaw_max) deg)"] | join(", "))"' "$body"
        # Each step's burst in step order, and the 0-based step of each frame.
        frames=() steps=() step=0
        for turn in $(jq -r '.steps[].turn' "$body"); do
            case "$turn" in
                front) burst=("${front[@]}") ;;
                left) burst=("${left[@]}") ;;
                right) burst=("${right[@]}") ;;
            esac
            for photo in "${burst[@]:0:$most}"; do
                frames+=(-F "frame=@$photo")
                steps+=("$step")
            done
            step=$((step + 1))
        done
        bursts=()
        if [[ ${#steps[@]} -gt $step ]]; then
            bursts=(--form-string "frame_steps=$(IFS=,; echo "${steps[*]}")")
        fi
        post /verify -F "subject=$subject" -F "image=@$probe" -F "challenge=$challenge" "${frames[@]}" "${bursts[@]}"
        [[ "$status" == 200 ]] || { refused; exit $?; }
        jq -r '"\(if .match then "match" else "no match" end): score \(.score), threshold \(.threshold) at FMR \(.fmr)"' "$body"
        jq -e '.liveness.challenge' "$body" >/dev/null || { echo "the server judged no challenge (liveness is off)" >&2; exit 4; }
        jq -r '.liveness.challenge.steps[] | "  \(.turn): yaw \(if .yaw == null then "unknown" else "\(.yaw * 10 | round / 10) deg" end), \(.frames) frame(s), \(if .ok then "ok" else "not ok" end)"' "$body"
        if ! jq -e .liveness.challenge.passed "$body" >/dev/null; then
            echo "the head-turn challenge failed: $(jq -r .liveness.challenge.reason "$body")" >&2
            exit 2
        fi
        echo "challenge passed"
        jq -e .match "$body" >/dev/null || exit 1 ;;
    *)
        echo "usage: $0 enroll SUBJECT PHOTO... | verify SUBJECT PHOTO [FMR] | verify-challenge SUBJECT PROBE --left PHOTO... --right PHOTO... [--front PHOTO...]" >&2
        exit 4 ;;
esac
