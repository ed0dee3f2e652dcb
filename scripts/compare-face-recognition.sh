#!/usr/bin/env bash
# Side by side with the Python face_recognition package (dlib's HOG detector, 5-point landmarks and
# the same ResNet), on the same photos in one run: CPU time per photo for the whole path (decode,
# detection, landmarks, alignment, network) and the equal error rate of the raw embedding distance
# over all pairs of the photos where both found a face. Installs face_recognition into a throwaway
# venv (PyPI); facegate runs from its release build. One core each (BLAS threads pinned to 1; CPU
# time is the process's own).
#   scripts/compare-face-recognition.sh [N_PERSONS]   (default 60 LFW test persons with ≥ 2 photos)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
persons="${1:-60}"
shared="${FACEGATE_SHARED:-../shared}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cargo build --release --quiet
python3 -m venv "$work/venv"
"$work/venv/bin/pip" install --quiet dlib-bin==20.0.1.post1 face_recognition_models==0.3.0 numpy pillow click
"$work/venv/bin/pip" install --quiet --no-deps face_recognition==1.3.0
# LFW test persons of facegate's split (eval::deep::lfw_split: first SHA-256 byte of the name mod 10 ≥ 8).
"$work/venv/bin/python" - "$shared/data/lfw" "$persons" > "$work/photos.txt" <<'PY'
import hashlib, os, sys
root, n = sys.argv[1], int(sys.argv[2])
people = sorted(p for p in os.listdir(root) if hashlib.sha256(p.encode()).digest()[0] % 10 >= 8)
people = [p for p in people if len(os.listdir(os.path.join(root, p))) >= 2][:n]
for p in people:
    for f in sorted(os.listdir(os.path.join(root, p))):
        print(os.path.join(root, p, f))
PY
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
xargs -d '\n' ./target/release/facegate embed < "$work/photos.txt" > "$work/facegate.jsonl"
"$work/venv/bin/python" - "$work/photos.txt" "$work/facegate.jsonl" <<'PY'
import json, sys, time
import numpy as np
import face_recognition
paths = [l.strip() for l in open(sys.argv[1]) if l.strip()]
ours = {}
for line in open(sys.argv[2]):
    o = json.loads(line)
    ours[o["image"]] = o
theirs, their_ms = {}, []
for p in paths:
    t = time.process_time()
    img = face_recognition.load_image_file(p)
    enc = face_recognition.face_encodings(img)
    their_ms.append((time.process_time() - t) * 1e3)
    if enc:
        theirs[p] = np.array(enc[0])
our_ms = [ours[p]["cpu_ms"] for p in paths if ours.get(p, {}).get("cpu_ms") is not None]
both = [p for p in paths if p in theirs and ours.get(p, {}).get("embedding")]
def eer(emb):
    g, i = [], []
    for a in range(len(both)):
        for b in range(a + 1, len(both)):
            d = float(np.linalg.norm(emb[both[a]] - emb[both[b]]))
            (g if both[a].split("/")[-2] == both[b].split("/")[-2] else i).append(-d)
    g, i = np.array(g), np.array(i)
    ts = np.unique(np.concatenate([g, i]))
    best = min(ts, key=lambda t: abs((g < t).mean() - (i >= t).mean()))
    return 100 * ((g < best).mean() + (i >= best).mean()) / 2, len(g), len(i)
ours_emb = {p: np.array(ours[p]["embedding"]) for p in both}
e_ours, e_theirs = eer(ours_emb), eer(theirs)
print(f"photos: {len(paths)}; face found: facegate {sum(1 for p in paths if ours.get(p, {}).get('embedding'))}, face_recognition {len(theirs)}; both {len(both)}")
print(f"CPU per photo (mean): facegate {np.mean(our_ms):.1f} ms, face_recognition {np.mean(their_ms):.1f} ms; ratio {np.mean(their_ms) / np.mean(our_ms):.2f}x")
print(f"EER of the raw embedding distance, all pairs of the {len(both)} photos ({e_ours[1]} genuine, {e_ours[2]} impostor): facegate {e_ours[0]:.2f}%, face_recognition {e_theirs[0]:.2f}%")
PY
