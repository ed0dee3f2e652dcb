#!/usr/bin/env bash
# Rebuilds tests/data/embedding-reference.json: dlib's own embeddings (the reference implementation,
# dlib-bin from PyPI in a throwaway venv) of the chips the embedding test cuts from ../shared photos.
# One-off; the test suite only reads the JSON. Needs network access to PyPI.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet dlib-bin==20.0.1.post1 numpy pillow face_recognition_models==0.3.0
mkdir -p "$work/chips"
FACEGATE_WRITE_REFERENCE_CHIPS="$work/chips" cargo test --lib embed::tests::embeddings_match -- --exact embed::tests::embeddings_match_dlib_within_cosine_0_999 >/dev/null 2>&1 || true
"$work/venv/bin/python" - "$work/chips" tests/data/embedding-reference.json <<'PY'
import json, os, sys
import dlib, numpy as np
from PIL import Image
import face_recognition_models as m
rec = dlib.face_recognition_model_v1(m.face_recognition_model_location())
out = {"source": f"dlib {dlib.__version__} compute_face_descriptor, face_recognition_models 0.3.0", "embeddings": {}}
for f in sorted(os.listdir(sys.argv[1])):
    chip = np.array(Image.open(os.path.join(sys.argv[1], f)).convert("RGB"))
    out["embeddings"][f[:-4].replace("__", "/")] = [float(v) for v in rec.compute_face_descriptor(chip)]
assert len(out["embeddings"]) == 5, out["embeddings"].keys()
json.dump(out, open(sys.argv[2], "w"), indent=1)
print(f"wrote {sys.argv[2]}: {len(out['embeddings'])} embeddings")
PY
