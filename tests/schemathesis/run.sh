#!/usr/bin/env bash
# schemathesis against the real server: every operation of ./openapi.yaml with generated valid
# and invalid requests (bounded: MAX_EXAMPLES per operation, default 30, a fixed seed), every
# check on; zero failures or the script fails. Uses target/debug/facegate as `cargo test` built it
# (FACEGATE_BIN overrides; nothing is built here), started on a free loopback port with a fresh
# database and the committed models, and stopped at the end. schemathesis is installed from PyPI
# (tests/schemathesis/requirements.txt) into a throwaway venv.
#
#   tests/schemathesis/run.sh
#   MAX_EXAMPLES=200 tests/schemathesis/run.sh
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
cd "$root"
bin="${FACEGATE_BIN:-target/debug/facegate}"
[[ -x "$bin" ]] || { echo "schemathesis: no $bin; run cargo test (or cargo build) first" >&2; exit 1; }
max_examples="${MAX_EXAMPLES:-30}"

work="$(mktemp -d)"
server=""
cleanup() {
    if [[ -n "$server" ]]; then kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; fi
    rm -rf "$work"
}
trap cleanup EXIT

python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet --disable-pip-version-check -r "$here/requirements.txt" </dev/null

NO_COLOR=1 RUST_LOG=warn,facegate::cli::serve=info "$bin" serve --bind 127.0.0.1:0 --database "sqlite://$work/facegate.db" \
    --models models >"$work/server.log" 2>&1 &
server=$!
base=""
for _ in $(seq 1 300); do
    base="$(grep -o 'listening on http://127\.0\.0\.1:[0-9]*' "$work/server.log" | sed 's/listening on //' || true)"
    [[ -n "$base" ]] && break
    kill -0 "$server" 2>/dev/null || break
    sleep 0.1
done
[[ -n "$base" ]] || { echo "schemathesis: the server did not start" >&2; cat "$work/server.log" >&2; exit 1; }

set +e
# From the temporary folder: schemathesis keeps its example cache in the working directory.
(cd "$work" && "$work/venv/bin/schemathesis" --no-color --config-file "$here/schemathesis.toml" run "$root/openapi.yaml" \
    --url "$base" --checks all --max-examples "$max_examples" --seed 15 --workers 1 --request-timeout 60 </dev/null)
status=$?
set -e
if grep -qiE 'panicked|internal error' "$work/server.log"; then
    echo "schemathesis: the server logged a panic or an internal error:" >&2
    grep -iE 'panicked|internal error' "$work/server.log" | head -20 >&2
    status=1
fi
exit "$status"
