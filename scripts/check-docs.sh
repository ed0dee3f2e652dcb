#!/usr/bin/env bash
# Documentation checks, no build needed: run from anywhere, e.g. `scripts/check-docs.sh`.
# Fails (exit 1, naming file:line) when
#   - README.md or any docs/**/*.md holds a git conflict marker line (<<<<<<< , =======, >>>>>>> ),
#   - README.md is longer than 220 lines,
#   - README.md, docs/, scripts/, models/ or the sources hold work-log residue ("session N", "round N", "stop N",
#     "issue N", "issue #N", "(#N)"): the tracker's history lives in git, the text says what is.
set -euo pipefail

cd "$(dirname "$0")/.."

readme_limit=220
failed=0

fail() {
    echo "$1" >&2
    failed=1
}

# README.md and every Markdown file under docs/, NUL-separated (names may hold spaces).
markdown=(README.md)
while IFS= read -r -d '' file; do
    markdown+=("$file")
done < <(find docs -type f -name '*.md' -print0 | sort -z)

# grep_hits GREP-ARGS...: grep's output (file:line:text) into $hits; 0 = found, 1 = none,
# anything else (an unreadable file, a bad pattern) stops the check.
grep_hits() {
    local status=0
    hits=$(grep "$@") || status=$?
    if ((status > 1)); then
        echo "check-docs: grep failed (status $status): grep $*" >&2
        exit 2
    fi
    return "$status"
}

if grep_hits -nHE '^(<<<<<<< |=======$|>>>>>>> )' -- "${markdown[@]}"; then
    while IFS= read -r hit; do
        fail "$(cut -d: -f1,2 <<<"$hit"): git conflict marker"
    done <<<"$hits"
fi

lines=$(wc -l <README.md)
if ((lines > readme_limit)); then
    fail "README.md:$lines: $lines lines, more than $readme_limit"
fi

# Work-log residue (case-insensitive; binary files skipped).
residue='session[- ][0-9]|round [0-9]|\bstop [0-9]+\b|\bissues? #?[0-9]+|\(#[0-9]+[),]'
if grep_hits -rnHiIE "$residue" -- README.md docs scripts models crates src tests; then
    while IFS= read -r hit; do
        fail "$(cut -d: -f1,2 <<<"$hit"): work-log residue: $(cut -d: -f3- <<<"$hit")"
    done <<<"$hits"
fi

if ((failed)); then
    exit 1
fi
echo "docs: ok"
