#!/usr/bin/env bash
# facegate with curl and jq: enrol photos, verify a probe.
#
#   ./facegate_example.sh enroll alice alice-1.jpg alice-2.jpg
#   ./facegate_example.sh verify alice probe.jpg [FMR]        # e.g. 1e-4
#
# FACEGATE_URL (default http://127.0.0.1:8080) and FACEGATE_API_KEY (if the server has keys) set the
# server. Exit status: 0 enrolled / match, 1 no match, 2 a photo is unusable (no face, a printed photo, ...),
# 3 model mismatch (enrol the subject again), 4 any other error.
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
    case "$problem" in
        no-face | several-faces | presentation-attack | not-an-image | corrupt-image | unsupported-format | too-large)
            echo "photo $(jq -r ".image // 0" "$body") refused: $(jq -r .detail "$body") ($problem); take another photo" >&2
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
    *)
        echo "usage: $0 enroll SUBJECT PHOTO... | verify SUBJECT PHOTO [FMR]" >&2
        exit 4 ;;
esac
