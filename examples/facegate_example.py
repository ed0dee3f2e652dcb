#!/usr/bin/env python3
"""facegate from Python with httpx (`pip install httpx`): enrol photos, verify a probe, verify with
a head-turn challenge (active liveness).

    python facegate_example.py enroll alice alice-1.jpg alice-2.jpg
    python facegate_example.py verify alice probe.jpg [--fmr 1e-4]
    python facegate_example.py verify-challenge alice probe.jpg --left l.jpg [--left l2.jpg] --right r.jpg [--front f.jpg]

verify-challenge asks for a challenge (POST /liveness/challenge), answers each step with the photos
given for its turn (`front` defaults to the probe; a real client takes a short burst of camera
frames per step, well inside the step's yaw range) and verifies the probe with them. An option
given more than once makes a burst: each step gets all its turn's photos (at most the challenge's
`max_frames_per_step`), sent with `frame_steps`; with one photo per turn, one frame per step.

FACEGATE_URL (default http://127.0.0.1:8080) and FACEGATE_API_KEY (if the server has keys) set the
server. Exit status: 0 enrolled / match, 1 no match, 2 a photo is unusable (no face, a printed photo,
a failed challenge, ...), 3 model mismatch (enrol the subject again), 4 any other error.
"""

import argparse
import os
import sys
import time
from pathlib import Path

import httpx

PROBLEMS = "https://facegate.dev/problems/"


class Problem(Exception):
    """An application/problem+json answer: `slug` is the type's last segment (`no-face`, ...)."""

    def __init__(self, body: dict):
        self.slug = body["type"].removeprefix(PROBLEMS)
        self.status, self.detail, self.image = body["status"], body["detail"], body.get("image")
        # `frame`: the further frame at fault; `reason`: why a head-turn challenge failed.
        self.frame, self.reason = body.get("frame"), body.get("reason")
        super().__init__(f"{self.slug} ({self.status}): {self.detail}")


def post(client: httpx.Client, path: str, fields: dict, photos: list[Path], params=None, attempts: int = 5,
         frames: list[Path] = ()) -> dict:
    """POST multipart (photos as `image` file parts, then `frames` as `frame` parts; no body when
    there is nothing to send); retry `overloaded` after Retry-After seconds."""
    files = [("image", (p.name, p.read_bytes(), "application/octet-stream")) for p in photos]
    files += [("frame", (p.name, p.read_bytes(), "application/octet-stream")) for p in frames]
    for attempt in range(1, attempts + 1):
        r = client.post(path, data=fields, files=files, params=params)
        if r.headers.get("content-type", "").startswith("application/problem+json"):
            problem = Problem(r.json())
            if problem.slug == "overloaded" and attempt < attempts:
                delay = float(r.headers.get("retry-after", "1"))
                print(f"facegate is busy; retrying in {delay:g} s", file=sys.stderr)
                time.sleep(delay)
                continue
            raise problem
        r.raise_for_status()
        return r.json()
    raise AssertionError("unreachable")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    enroll = commands.add_parser("enroll", help="enrol (or add photos to) a subject")
    enroll.add_argument("subject")
    enroll.add_argument("photos", nargs="+", type=Path)
    verify = commands.add_parser("verify", help="is the probe's largest face the subject?")
    verify.add_argument("subject")
    verify.add_argument("photo", type=Path)
    verify.add_argument("--fmr", type=float, help="false match rate of the operating point (default 1e-3)")
    challenge = commands.add_parser("verify-challenge", help="verify the probe with a head-turn challenge")
    challenge.add_argument("subject")
    challenge.add_argument("photo", type=Path, help="the probe, looking at the camera")
    # Each may be given more than once: the step's burst.
    challenge.add_argument("--front", type=Path, action="append", help="a photo looking at the camera (default: the probe)")
    challenge.add_argument("--left", type=Path, action="append", required=True, help="a photo turned to the person's own left")
    challenge.add_argument("--right", type=Path, action="append", required=True, help="a photo turned to the person's own right")
    args = parser.parse_args()

    key = os.environ.get("FACEGATE_API_KEY")
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    base_url = os.environ.get("FACEGATE_URL", "http://127.0.0.1:8080")
    with httpx.Client(base_url=base_url, headers=headers, timeout=60) as client:
        try:
            if args.command == "enroll":
                e = post(client, "/enroll", {"subject": args.subject}, args.photos)
                print(f"enrolled {e['subject']}: {e['added']} template(s) added, {e['templates']} in all")
                return 0
            if args.command == "verify-challenge":
                return verify_challenge(client, args)
            params = {"fmr": args.fmr} if args.fmr else None
            v = post(client, "/verify", {"subject": args.subject}, [args.photo], params)
            verdict = "match" if v["match"] else "no match"
            print(f"{verdict}: score {v['score']:.3f}, threshold {v['threshold']:.3f} at FMR {v['fmr']:g}")
            return 0 if v["match"] else 1
        except Problem as p:
            if p.reason:
                print(f"the head-turn challenge failed: {p.reason} ({p.slug})", file=sys.stderr)
                return 2
            if p.slug in ("no-face", "several-faces", "presentation-attack", "not-an-image", "corrupt-image", "unsupported-format", "too-large"):
                photos = args.photos if args.command == "enroll" else [args.photo]
                which = photos[p.image or 0] if p.frame is None else f"frame {p.frame + 1}"
                print(f"{which}: {p.detail} ({p.slug}); take another photo", file=sys.stderr)
                return 2
            if p.slug == "model-mismatch":
                print(f"{args.subject} was enrolled with another model version: enrol the subject again", file=sys.stderr)
                return 3
            print(f"facegate refused: {p}", file=sys.stderr)
            return 4
        except httpx.HTTPError as e:
            print(f"request to facegate at {base_url} failed: {e}", file=sys.stderr)
            return 4


def verify_challenge(client: httpx.Client, args) -> int:
    """Ask for a challenge, answer each step with the photos of its turn, verify; print the outcome."""
    c = post(client, "/liveness/challenge", {}, [])
    photos = {"front": args.front or [args.photo], "left": args.left, "right": args.right}
    steps = c["steps"]
    print(f"challenge of {len(steps)} steps: " + ", ".join(f"{s['turn']} ({s['yaw_min']:g}..{s['yaw_max']:g} deg)" for s in steps))
    bursts = [photos[s["turn"]][: c.get("max_frames_per_step", 5)] for s in steps]
    frames = [photo for burst in bursts for photo in burst]
    fields = {"subject": args.subject, "challenge": c["challenge"]}
    if len(frames) > len(steps):
        # Bursts: the 0-based step of each frame, in order.
        fields["frame_steps"] = ",".join(str(i) for i, burst in enumerate(bursts) for _ in burst)
    v = post(client, "/verify", fields, [args.photo], frames=frames)
    verdict = "match" if v["match"] else "no match"
    print(f"{verdict}: score {v['score']:.3f}, threshold {v['threshold']:.3f} at FMR {v['fmr']:g}")
    outcome = (v.get("liveness") or {}).get("challenge")
    if outcome is None:
        print("the server judged no challenge (liveness is off)", file=sys.stderr)
        return 4
    for s in outcome["steps"]:
        yaw = "unknown" if s["yaw"] is None else f"{s['yaw']:.1f} deg"
        print(f"  {s['turn']}: yaw {yaw}, {s['frames']} frame(s), {'ok' if s['ok'] else 'not ok'}")
    if not outcome["passed"]:
        print(f"the head-turn challenge failed: {outcome['reason']}", file=sys.stderr)
        return 2
    print("challenge passed")
    return 0 if v["match"] else 1


if __name__ == "__main__":
    sys.exit(main())
