#!/usr/bin/env bash
# The one-off reference measurement behind the choice of the protected template scheme
# (docs/template-protection.md): the service's own fused templates of every LFW, IMM and
# ORL photo, then BioHashing, Index-of-Max hashing, top-k signs, quantised and plain keyed
# rotations against the plain templates: EER and FNMR at FMR 1e-3 on LFW test persons,
# unlinkability (D<->sys, Gomez-Barrero et al. 2018) across two secrets and with one, the best
# inversion attack with the secret and one protected template, size and speed. Python (numpy,
# scipy, requests, Pillow) in a throwaway venv; nothing here runs in the service.
#
#   cargo build --release && scripts/protection-reference/run.sh    # about 2 hours on 2 cores
#
# Work folder: target/protection-reference (the database, templates.npz, results.jsonl, table.md).
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
work="$root/target/protection-reference"
export FACEGATE_SHARED_DATA="${FACEGATE_SHARED:-$root/../shared}/data"
mkdir -p "$work"
cp "$root"/scripts/protection-reference/*.py "$work/"
cd "$work"
[ -d venv ] || { python3 -m venv venv && venv/bin/pip install -q numpy scipy requests pillow; }
"$root/target/release/facegate" serve --bind 127.0.0.1:18555 --database "sqlite://$work/t.db" --models "$root/models" \
    --workers 1 --console false --liveness off >server.log 2>&1 &
server=$!
trap 'kill $server 2>/dev/null || true' EXIT
for _ in $(seq 600); do curl -sf http://127.0.0.1:18555/livez >/dev/null && break; sleep 0.2; done
venv/bin/python enroll.py          # every photo, its own subject (enroll_log.jsonl)
venv/bin/python enroll_crops.py    # photos refused for several faces, again from the largest face's crop
kill $server; trap - EXIT
venv/bin/python load_templates.py  # templates.npz, the project's person split
venv/bin/python evaluate.py        # the grid (results.jsonl)
venv/bin/python gibbs_attack.py    # the sampled attack on the rotation codes (results_gibbs.jsonl)
venv/bin/python extra.py           # more secret pairs, larger pair sets (extra.json)
venv/bin/python bench.py           # comparison time and size
venv/bin/python make_table.py      # table.md
