"""Second pass: photos refused with `several-faces` are cropped around the largest face
(/analyze?faces=largest box, expanded by a margin) and enrolled again under the same subject id.
Logged to crop_log.jsonl (these are flagged `cropped` in the evaluation)."""
import io, json, os, time, concurrent.futures as cf
import requests
from PIL import Image

URL = os.environ.get("FG_URL", "http://127.0.0.1:18555")
DATA = os.environ.get("FACEGATE_SHARED_DATA", "../../../../shared/data")
LOG = "crop_log.jsonl"

def attempt(x):
    path = {"lfw": f"{DATA}/lfw/{x['person']}/{x['photo']}", "imm": f"{DATA}/imm/{x['photo']}",
            "orl": f"{DATA}/orl/{x['person']}/{x['photo']}"}[x["set"]]
    raw = open(path, "rb").read()
    r = requests.post(f"{URL}/analyze?faces=largest", files={"image": ("p", raw)}, timeout=120)
    res = dict(subject=x["subject"], status=None, margin=None)
    if r.status_code != 200:
        res["status"] = f"analyze {r.status_code}"; return res
    faces = r.json().get("faces") or []
    if not faces:
        res["status"] = "analyze no face"; return res
    b = faces[0]["face"]["box"]
    img = Image.open(io.BytesIO(raw)).convert("RGB")
    for margin in (0.5, 0.3, 0.15):
        x0 = max(0, int(b["x"] - margin * b["width"])); y0 = max(0, int(b["y"] - margin * b["height"]))
        x1 = min(img.width, int(b["x"] + (1 + margin) * b["width"])); y1 = min(img.height, int(b["y"] + (1 + margin) * b["height"]))
        buf = io.BytesIO(); img.crop((x0, y0, x1, y1)).save(buf, "PNG")
        e = requests.post(f"{URL}/enroll", data={"subject": x["subject"]}, files={"image": ("c.png", buf.getvalue())}, timeout=120)
        res["status"], res["margin"], res["body"] = e.status_code, margin, e.text[:200]
        if e.status_code == 201 or "several-faces" not in e.text:
            break
    return res

def main():
    log = [json.loads(l) for l in open("enroll_log.jsonl")]
    todo = [x for x in log if x["status"] == 422 and "several-faces" in x["body"]]
    done = set()
    if os.path.exists(LOG):
        done = {json.loads(l)["subject"] for l in open(LOG)}
    todo = [x for x in todo if x["subject"] not in done]
    order = {"test": 0, "calibration": 1, "train": 2}
    todo.sort(key=lambda x: order[x["split"]])
    print("to crop:", len(todo), flush=True)
    with open(LOG, "a") as f, cf.ThreadPoolExecutor(2) as ex:
        for k, res in enumerate(ex.map(attempt, todo)):
            f.write(json.dumps(res) + "\n"); f.flush()
            if k % 50 == 0: print(k, res["status"], res["subject"], flush=True)

if __name__ == "__main__":
    main()
