"""Enrol every evaluation photo as its own subject through the running facegate server.
Order: LFW test persons, IMM/ORL held-out persons, then LFW calibration, then LFW training (as time allows).
Split reproduced from crates/research/src/dataset.rs (lfw_split, imm_is_test_person)."""
import hashlib, json, os, re, sys, time, concurrent.futures as cf
import requests

DATA = os.environ.get("FACEGATE_SHARED_DATA", "../../../../shared/data")
URL = os.environ.get("FG_URL", "http://127.0.0.1:18555")
LOG = "enroll_log.jsonl"
IMG = {"jpg", "jpeg", "png", "gif", "pgm", "ppm", "bmp"}

def lfw_split(person):
    h = hashlib.sha256(person.encode()).digest()[0] % 10
    return "train" if h <= 5 else ("calibration" if h <= 7 else "test")

def imm_is_test_person(n):
    return n <= 3 or n % 5 == 0

def listing():
    out = []  # (set, person, photo, path, split)
    d = f"{DATA}/lfw"
    for p in sorted(os.listdir(d)):
        for f in sorted(os.listdir(f"{d}/{p}")):
            if f.rsplit(".", 1)[-1].lower() in IMG:
                out.append(("lfw", p, f, f"{d}/{p}/{f}", lfw_split(p)))
    d = f"{DATA}/imm"
    for f in sorted(os.listdir(d)):
        m = re.match(r"^(\d+)-(\d+)", f)
        if m and f.rsplit(".", 1)[-1].lower() in IMG:
            n = int(m.group(1))
            out.append(("imm", f"{n:02}", f, f"{d}/{f}", "test" if imm_is_test_person(n) else "train"))
    d = f"{DATA}/orl"
    for p in sorted(os.listdir(d)):
        if os.path.isdir(f"{d}/{p}"):
            n = int(p.lstrip("s"))
            for f in sorted(os.listdir(f"{d}/{p}")):
                if f.rsplit(".", 1)[-1].lower() in IMG:
                    out.append(("orl", p, f, f"{d}/{p}/{f}", "test" if imm_is_test_person(n) else "train"))
    return out

def sid(s, person, photo):
    x = re.sub(r"[^A-Za-z0-9._-]", "_", f"{s}__{person}__{photo.rsplit('.',1)[0]}")
    return x[:128]

def enrol(item):
    s, person, photo, path, split = item
    subject = sid(s, person, photo)
    t = time.time()
    with open(path, "rb") as fh:
        r = requests.post(f"{URL}/enroll", data={"subject": subject}, files={"image": (photo, fh, "application/octet-stream")}, timeout=120)
    body = r.text[:300]
    return dict(set=s, person=person, photo=photo, split=split, subject=subject, status=r.status_code, body=body, secs=time.time() - t)

def main():
    order = {("lfw", "test"): 0, ("imm", "test"): 1, ("orl", "test"): 1, ("lfw", "calibration"): 2, ("lfw", "train"): 3, ("imm", "train"): 4, ("orl", "train"): 4}
    items = sorted(listing(), key=lambda x: order[(x[0], x[4])])
    done = set()
    if os.path.exists(LOG):
        for line in open(LOG):
            done.add(json.loads(line)["subject"])
    items = [i for i in items if sid(i[0], i[1], i[2]) not in done]
    limit = int(sys.argv[1]) if len(sys.argv) > 1 else len(items)
    items = items[:limit]
    print("to enrol:", len(items), flush=True)
    t0 = time.time()
    with open(LOG, "a") as log, cf.ThreadPoolExecutor(2) as ex:
        for k, res in enumerate(ex.map(enrol, items)):
            log.write(json.dumps(res) + "\n"); log.flush()
            if k % 100 == 0:
                print(k, f"{time.time()-t0:.0f}s", res["status"], res["subject"], flush=True)

if __name__ == "__main__":
    main()
