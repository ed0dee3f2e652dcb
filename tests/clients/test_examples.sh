#!/usr/bin/env bash
# The examples in examples/ against a running facegate, run by tests/clients/run.sh with:
# BASE (the server), STUB (tests/clients/overload_stub.py in front of it), ENFORCE (a server with
# --liveness enforce), IMM (the IMM photos), NUAA (the NUAA live and print frames), GREY (a
# face-free photo), PYTHON (a python with httpx), TS_EXAMPLE (the compiled TypeScript example), and
# a subject `legacy` whose only template is of another model version.
# Closes with "examples: N passed, M failed"; exits non-zero on any failure.
set -uo pipefail
examples="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../examples" && pwd)"
out="$(mktemp)" err="$(mktemp)"
trap 'rm -f "$out" "$err"' EXIT
passed=0 failed=0

# record OK NAME: count a check (OK 0 passed) and say so; a failed one shows the last run's
# stdout and stderr.
record() {
    if [[ $1 == 0 ]]; then
        passed=$((passed + 1))
        echo "ok   examples $lang $2"
    else
        failed=$((failed + 1))
        echo "FAIL examples $lang $2"
        sed 's/^/    stdout: /' "$out"
        sed 's/^/    stderr: /' "$err"
    fi
}

# expect LANG STATUS STDOUT-PATTERN STDERR-PATTERN URL -- ARGS...: run the example of LANG with ARGS
# against URL; its exit status must be STATUS and its outputs must match the (grep -E) patterns
# (an empty pattern checks nothing).
expect() {
    local lang="$1" want="$2" out_pattern="$3" err_pattern="$4" url="$5" status=0
    shift 6
    case "$lang" in
        python) FACEGATE_URL="$url" "$PYTHON" "$examples/facegate_example.py" "$@" >"$out" 2>"$err" || status=$? ;;
        typescript) FACEGATE_URL="$url" node "$TS_EXAMPLE" "$@" >"$out" 2>"$err" || status=$? ;;
        curl)
            local args=("$@")
            # The curl example takes the FMR as a fourth argument instead of --fmr.
            [[ "${args[3]:-}" == --fmr ]] && args=("${args[@]:0:3}" "${args[4]}")
            FACEGATE_URL="$url" "$examples/facegate_example.sh" "${args[@]}" >"$out" 2>"$err" || status=$?
            ;;
    esac
    if [[ $status == "$want" ]] && { [[ -z "$out_pattern" ]] || grep -Eq "$out_pattern" "$out"; } &&
        { [[ -z "$err_pattern" ]] || grep -Eq "$err_pattern" "$err"; }; then
        record 0 "$*"
    else
        record 1 "$*: exit $status (wanted $want)"
    fi
}

# every_step N: every step line the last run printed says N frame(s) and ok (a step's burst as
# the server counted it, `steps[i].frames`).
every_step() {
    local steps
    steps="$(grep -E '^  (front|left|right): yaw ' "$out" || true)"
    [[ $(grep -c . <<<"$steps") -ge 3 ]] && ! grep -vqE ", $1 frame\(s\), ok$" <<<"$steps"
    record $? "every step answered by $1 frame(s)"
}

for lang in python typescript curl; do
    s="ex-$lang"
    expect "$lang" 0 "^enrolled $s: 2 template" '' "$BASE" -- enroll "$s" "$IMM/01-1m.jpg" "$IMM/01-3m.jpg"
    expect "$lang" 0 '^match: .*FMR 0?\.0001|^match: .*FMR 1e-4' '' "$BASE" -- verify "$s" "$IMM/01-5m.jpg" --fmr 1e-4
    expect "$lang" 1 '^no match: ' '' "$BASE" -- verify "$s" "$IMM/02-4m.jpg"
    expect "$lang" 2 '' 'no-face' "$BASE" -- verify "$s" "$GREY"
    expect "$lang" 2 '' 'no-face' "$BASE" -- enroll "$s" "$IMM/01-2m.jpg" "$GREY"
    expect "$lang" 3 '' 'enrol the subject again' "$BASE" -- verify legacy "$IMM/01-2m.jpg"
    expect "$lang" 0 '^match: ' 'busy; retrying in 1 s' "$STUB" -- verify "$s" "$IMM/01-5m.jpg"
    # Under --liveness enforce: a live frame enrols, a printed photo of the same person is refused.
    expect "$lang" 0 "^enrolled $s: 1 template" '' "$ENFORCE" -- enroll "$s" "$NUAA/real/0004/0004_01_00_02_134.jpg"
    expect "$lang" 2 '' 'presentation-attack' "$ENFORCE" -- verify "$s" "$NUAA/print/0004/0004_01_01_03_211.jpg"
    # The head-turn challenge with IMM person 15: a burst of two photos per turn (frame_steps: both
    # frontal views ahead, each turned view twice) passes, and so does one photo per turn (one
    # frame per step, no frame_steps); frontal photos for the turns fail it (reported under
    # --liveness report, refused under enforce), saying why.
    t="$s-turns" turns=(--front "$IMM/15-5f.jpg" --left "$IMM/15-4f.jpg" --right "$IMM/15-3f.jpg")
    bursts=(--front "$IMM/15-5f.jpg" --front "$IMM/15-1f.jpg" --left "$IMM/15-4f.jpg" --left "$IMM/15-4f.jpg"
        --right "$IMM/15-3f.jpg" --right "$IMM/15-3f.jpg")
    expect "$lang" 0 "^enrolled $t: 2 template" '' "$BASE" -- enroll "$t" "$IMM/15-1f.jpg" "$IMM/15-2f.jpg"
    expect "$lang" 0 '^challenge passed' '' "$BASE" -- verify-challenge "$t" "$IMM/15-2f.jpg" "${bursts[@]}"
    every_step 2
    expect "$lang" 0 '^challenge passed' '' "$BASE" -- verify-challenge "$t" "$IMM/15-2f.jpg" "${turns[@]}"
    every_step 1
    expect "$lang" 2 '^match: ' 'challenge failed: .' "$BASE" -- verify-challenge "$t" "$IMM/15-2f.jpg" --left "$IMM/15-1f.jpg" --right "$IMM/15-1f.jpg"
    expect "$lang" 0 "^enrolled $t: 2 template" '' "$ENFORCE" -- enroll "$t" "$IMM/15-1f.jpg" "$IMM/15-2f.jpg"
    expect "$lang" 0 '^challenge passed' '' "$ENFORCE" -- verify-challenge "$t" "$IMM/15-2f.jpg" "${bursts[@]}"
    every_step 2
    expect "$lang" 2 '' 'challenge failed: .*presentation-attack' "$ENFORCE" -- verify-challenge "$t" "$IMM/15-2f.jpg" \
        --left "$IMM/15-5f.jpg" --left "$IMM/15-1f.jpg" --right "$IMM/15-1f.jpg" --right "$IMM/15-5f.jpg"
done
echo "examples: $passed passed, $failed failed"
[[ $failed == 0 ]]
