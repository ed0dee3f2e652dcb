"""Read the templates table of t.db (plain little-endian f32, crates/store/src/codec.rs) and
write templates.npz: X (N x 256 fused vectors), set, person, photo, split, cropped."""
import json, sqlite3, numpy as np

DB = "file:t.db?mode=ro"
log = {}
for line in open("enroll_log.jsonl"):
    x = json.loads(line); log[x["subject"]] = x
cropped = set()
try:
    for line in open("crop_log.jsonl"):
        x = json.loads(line)
        if x["status"] == 201: cropped.add(x["subject"])
except FileNotFoundError:
    pass
con = sqlite3.connect(DB, uri=True)
rows = con.execute("SELECT subject_id, model_version, dimension, vector FROM templates ORDER BY subject_id, id").fetchall()
X, meta, versions = [], [], set()
for subject, version, dim, blob in rows:
    assert len(blob) == 4 * dim, "sealed template? (expected plain f32)"
    v = np.frombuffer(blob, "<f4").astype(np.float64)
    versions.add((version, dim))
    e = log[subject]
    X.append(v); meta.append((e["set"], e["person"], e["photo"], e["split"], subject in cropped))
X = np.array(X)
print("templates", X.shape, "versions", versions)
n1, n2 = (X[:, :128] ** 2).sum(1), (X[:, 128:] ** 2).sum(1)
print("member block squared norms (weights): dlib %.5f..%.5f  sface %.5f..%.5f" % (n1.min(), n1.max(), n2.min(), n2.max()))
m = np.array(meta, dtype=object)
np.savez("templates.npz", X=X, set=m[:, 0].astype(str), person=m[:, 1].astype(str), photo=m[:, 2].astype(str),
         split=m[:, 3].astype(str), cropped=m[:, 4].astype(bool))
