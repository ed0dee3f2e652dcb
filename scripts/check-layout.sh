#!/usr/bin/env bash
# The layout rules no compiler checks (docs/architecture.md): no Rust source file over 800 lines,
# no module of the binary outside src/cli importing the command line, no crate re-exporting a
# sibling crate or its items (and no old path through such a re-export), and no runtime crate (core, detect, nn, morph, vision, store, service, http) depending on what the runtime must not
# reach — the research crate, the binary, the settings' paths, clap or indicatif. Function length,
# printing and environment reads are clippy's (the workspace lints; CI runs clippy on the runtime).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
python3 - <<'PY'
import json, pathlib, subprocess, sys

failures = []
for path in sorted(pathlib.Path(".").glob("**/*.rs")):
    if path.parts[0] in ("target",) or "node_modules" in path.parts:
        continue
    lines = sum(1 for _ in path.open(encoding="utf-8"))
    if lines > 800:
        failures.append(f"{path}: {lines} lines (at most 800)")

# The command line is a leaf of the binary: nothing else in it imports `crate::cli`.
for path in sorted(pathlib.Path("src").glob("**/*.rs")):
    if path.parts[1] == "cli":
        continue
    for number, line in enumerate(path.open(encoding="utf-8"), 1):
        if "crate::cli" in line and not line.lstrip().startswith("//"):
            failures.append(f"{path}:{number}: imports the command line (take plain values or a callback instead)")

# Crates are called by their own names: no crate, and not the binary, re-exports a sibling crate or
# any of its items (a dependent declares the crate and imports the item from its home), and core's
# template types are named from core alone.
import re
sibling_reexport = re.compile(r"^\s*pub use (::)?facegate_\w+")
old_paths = re.compile(r"facegate_vision::(morph|detect)\b|\brecognize::(template::)?(Template|OperatingPoint)\b")
for path in sorted(pathlib.Path(".").glob("**/*.rs")):
    if path.parts[0] in ("target",) or "node_modules" in path.parts:
        continue
    for number, line in enumerate(path.open(encoding="utf-8"), 1):
        if line.lstrip().startswith("//"):
            continue
        if path.parts[0] in ("crates", "src") and sibling_reexport.match(line):
            failures.append(f"{path}:{number}: re-exports a sibling crate's item; its dependents declare the crate and import it from there")
        if old_paths.search(line):
            failures.append(f"{path}:{number}: an old path; name facegate_morph, facegate_detect or facegate_core::template")

runtime = {"facegate-core", "facegate-nn", "facegate-morph", "facegate-detect", "facegate-vision", "facegate-store", "facegate-service", "facegate-http"}
forbidden = {"facegate", "facegate-research", "facegate-paths", "clap", "indicatif"}
meta = json.loads(subprocess.run(["cargo", "metadata", "--format-version", "1", "--no-deps"], check=True,
                                 capture_output=True, text=True).stdout)
for package in meta["packages"]:
    if package["name"] not in runtime:
        continue
    for dep in package["dependencies"]:
        if dep["name"] in forbidden and dep["kind"] is None:
            failures.append(f"{package['name']} depends on {dep['name']}: the runtime must not")

# Research is handed its paths (by the binary's commands); the settings' paths are only its
# tests' (a dev-dependency).
for package in meta["packages"]:
    if package["name"] == "facegate-research":
        for dep in package["dependencies"]:
            if dep["name"] == "facegate-paths" and dep["kind"] is None:
                failures.append("facegate-research depends on facegate-paths: research takes the paths it is handed")

for failure in failures:
    print(f"layout: {failure}", file=sys.stderr)
if failures:
    sys.exit(1)
print("layout: ok")
PY
