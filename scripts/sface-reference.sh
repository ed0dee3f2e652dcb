#!/usr/bin/env bash
# Rebuilds tests/data/sface-reference.json: SFace's embeddings by the reference runtime
# (onnxruntime, from PyPI in a throwaway venv) of the central 112×112 pixels of three LFW photos
# (no resampling, so both runtimes see the same input). One-off; the test suite only reads the
# JSON. Needs network access to PyPI and models/sface.onnx (facegate convert sface).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet onnxruntime==1.20.1 numpy pillow
"$work/venv/bin/python" - ../shared/data/lfw models/sface.onnx tests/data/sface-reference.json <<'PY'
import json, sys
import numpy as np, onnxruntime as ort
from PIL import Image
lfw, model, out_path = sys.argv[1:4]
sess = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
name = sess.get_inputs()[0].name
out = {"source": f"onnxruntime {ort.__version__}, central 112x112 of the photo, RGB 0-255 NCHW", "embeddings": {}}
for photo in ["Hal_Sutton/Hal_Sutton_0001", "Judy_Genshaft/Judy_Genshaft_0002", "Hal_Sutton/Hal_Sutton_0002"]:
    rgb = np.asarray(Image.open(f"{lfw}/{photo}.jpg").convert("RGB"), dtype=np.float32)[69:181, 69:181]
    e = sess.run(None, {name: rgb.transpose(2, 0, 1)[None]})[0][0]
    out["embeddings"][photo] = [float(v) for v in e / np.linalg.norm(e)]
json.dump(out, open(out_path, "w"), indent=1)
print(f"wrote {out_path}: {len(out['embeddings'])} embeddings")
PY
