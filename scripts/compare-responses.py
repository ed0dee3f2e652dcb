#!/usr/bin/env python3
"""The same requests to two running servers, their answers compared: status, media type and the
JSON body without timings and per-request values (a refactor's check that nothing a client sees
changed). Binary bodies (PNG, YAML) are compared by SHA-256.

    python3 scripts/compare-responses.py --shared ../shared http://127.0.0.1:8792 http://127.0.0.1:8793

Each server should start on an empty database with the same settings: the requests enrol IMM
persons 01-03 and then verify and identify against them. Exits 1 when any answer differs.
"""
import argparse
import hashlib
import json
import subprocess
import sys

# Keys whose values differ from run to run, not from code to code.
VOLATILE = {"timings", "challenge", "created_at", "updated_at", "request_id", "expires_at"}


def stable(value):
    if isinstance(value, dict):
        return {k: stable(v) for k, v in value.items() if not (k.endswith("_ms") or k in VOLATILE)}
    if isinstance(value, list):
        return [stable(v) for v in value]
    return value


def call(base, method, path, fields, files):
    args = ["curl", "-s", "-w", "\n%{http_code} %{content_type}", "-X", method, base + path]
    for key, value in fields:
        args += ["-F", f"{key}={value}"]
    for key, file in files:
        args += ["-F", f"{key}=@{file}"]
    out = subprocess.run(args, capture_output=True, check=True).stdout
    body, status = out.rsplit(b"\n", 1)
    try:
        shown = json.dumps(stable(json.loads(body)), sort_keys=True)
    except ValueError:
        shown = f"<{len(body)} bytes, sha256 {hashlib.sha256(body).hexdigest()}>"
    return status.decode(), shown


def requests(shared):
    imm = f"{shared}/data/imm/"
    return [
        ("POST", "/analyze", [], [("image", imm + "01-1m.jpg")]),
        ("POST", "/analyze?faces=all", [], [("image", imm + "05-4m.jpg")]),
        ("POST", "/analyze", [], [("image", f"{shared}/data/orl/s1/1.pgm")]),
        ("POST", "/enroll", [("subject", "imm-01")], [("image", imm + "01-1m.jpg"), ("image", imm + "01-2m.jpg")]),
        ("POST", "/enroll", [("subject", "imm-02")], [("image", imm + "02-1m.jpg")]),
        ("POST", "/enroll", [("subject", "imm-03")], [("image", imm + "03-1m.jpg")]),
        ("POST", "/verify", [("subject", "imm-01")], [("image", imm + "01-3m.jpg")]),
        ("POST", "/verify", [("subject", "imm-01")], [("image", imm + "02-2m.jpg")]),
        ("POST", "/verify", [("subject", "imm-01")], [("image", imm + "01-5m.jpg"), ("frame", imm + "01-6m.jpg")]),
        ("POST", "/identify", [], [("image", imm + "02-2m.jpg")]),
        ("POST", "/identify", [], [("image", imm + "03-4m.jpg")]),
        ("POST", "/verify", [("subject", "nobody")], [("image", imm + "01-3m.jpg")]),
        ("POST", "/verify", [("subject", "imm-01")], [("image", imm + "01-1m.asf")]),
        ("POST", "/enroll", [], [("image", imm + "01-1m.jpg")]),
        ("GET", "/subjects", [], []),
        ("GET", "/subjects/imm-01", [], []),
        ("GET", "/health", [], []),
        ("GET", "/openapi.yaml", [], []),
        ("POST", "/frontalize", [], [("image", imm + "01-3m.jpg")]),
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", default="../shared")
    parser.add_argument("before")
    parser.add_argument("after")
    args = parser.parse_args()
    sent = requests(args.shared)
    different = 0
    for method, path, fields, files in sent:
        before = call(args.before, method, path, fields, files)
        after = call(args.after, method, path, fields, files)
        if before == after:
            print(f"same       {method} {path}: {before[0]}")
        else:
            different += 1
            print(f"different  {method} {path}\n  before {before[0]} {before[1][:600]}\n  after  {after[0]} {after[1][:600]}")
    print(f"{len(sent) - different} of {len(sent)} answers the same")
    sys.exit(1 if different else 0)


if __name__ == "__main__":
    main()
