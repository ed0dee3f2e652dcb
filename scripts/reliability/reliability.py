#!/usr/bin/env python3
"""The service under hostile load, against the real binary on 127.0.0.1 (stdlib only).

Each scenario starts `facegate serve` on a free loopback port with a fresh database, attacks it,
checks its target and prints one result line; the script exits non-zero if any failed.

  slowloris   1,000 half-open connections (`GET / HTTP/1.1\\r\\nX: `, then silence): all closed
              within the header timeout (+1 s of slack for 1,000 sockets on a busy machine)
  slow-body   60 uploads declaring 15 MB that stall after 1 MB: each answered 408
              `request-timeout` (or 503 when the body-memory budget is spent) within the body
              timeout (+1 s), and the server's peak RSS stays under 300 MB
  kill9       an enrolment storm (8 clients, distinct subjects) killed with SIGKILL after a few
              seconds, three times: every enrolment answered 201 is there after the restart
  sigterm     SIGTERM with an idle keep-alive connection and a stalled upload open: the process
              exits within the shutdown grace period (+1 s)
  stalled-heads
              86 request heads from 127.0.0.2 whose body never comes (8 declaring 16 MiB + 1 byte, over the limit;
              8 declaring 15 MiB; 70 declaring 125,000 bytes, over /verify /enroll /identify
              /analyze), each opened again once answered, for 12 s, against --workers 2 --queue 4
              --enrol-queue 2; meanwhile 4 clients run 48 verifications (IMM 01-1m enrolled, 01-2m
              the probe) paced over those 12 s: >= 95 % answered 200, and the over-limit heads
              answered 413 within 1 s
  json-flood  a 15 MB JSON body {"subject":"a","images":["AA", ... 3,000,000 times]} POSTed to
              /enroll once, then 4 at once (from 4 addresses): each answered 400 `malformed-request`, the server's
              peak RSS growth (VmHWM, reset when the flood starts, - VmRSS before) <= 50 MB for the
              one body (<= 50 MB plus
              the four bodies themselves, which the body budget counts, for the 4 at once), and
              /health (asked every 50 ms meanwhile) answered within 1 s
  trickle     8 connections that each send a `POST /verify` head declaring 16 MiB (the body limit)
              and then one byte a second, each opened again once answered, for 12 s, while a client
              verifies IMM 01-2m against the enrolled 01-1m one request after another (waiting the
              Retry-After second after a 503): >= 95 % of the
              verifications answered 200; then the same with the trickles on /enroll while the
              client alternates verifications and enrolments of new subjects: >= 95 % of each
              answered 200 / 201; then 66 trickles declaring 125,000 bytes on /verify (as many as
              the default queue has places) from another address, 127.0.0.2: >= 95 % of the
              verifications answered 200
  part-flood  one multipart body of a subject and 150,000 one-byte `image` parts (11 MB) POSTed to /enroll:
              answered 4xx, the server's peak RSS growth (VmHWM, reset first, - VmRSS before)
              <= 50 MB, and /health 200 afterwards
  duplicates  81 LFW persons enrolled (two photos each), 40 of them again under a second id (a third
              photo); each person's fourth photo verified, then `facegate calibrate` and a
              restart: the genuine verifications match at >= 95 % of the rate before, and
              calibrate names at least half of the 40 duplicates (scripts/reliability/duplicates.py)
  fail-closed the binary with `--api-keys ",,"`, with an --api-keys-file of comment lines only, and
              on a database sealed under one template key started without a key and with another:
              each exits non-zero within 30 s and never prints "listening on" (the control: the
              first key still opens the sealed database)
  db-down     PostgreSQL as the store (a throwaway cluster from initdb/pg_ctl, run as the postgres
              user when this runs as root; the server with --timeout-secs 4): 2 clients verify an
              enrolled subject's genuine probe and enrol new subjects (a fresh id per attempt, 5 s
              client timeout) while PostgreSQL is stopped hard (pg_ctl stop -m immediate) for 10 s
              and started again for 10 s: while it is down, every request answered within 2 s (503
              `store-unavailable` with Retry-After, or a success); success again within 5 s of the
              restart; 0 wrong answers; 0 enrolments answered 201 missing at the end; 0 answered
              503/504 present at the end. Without initdb it is skipped with the reason, unless
              FACEGATE_REQUIRE_POSTGRES=1 (CI), which makes that a failure
  secrets     `serve` (text and JSON logs) and `calibrate` on an unreachable PostgreSQL, the password
              in the URL or in --database-password-file: each exits non-zero and prints no password
  challenge-flood
              POST /liveness/challenge from 8 keep-alive connections of 127.0.0.1 for 10 s: only
              201 and 429 (with Retry-After), <= 2,000 challenge rows in the database, and 127.0.0.2
              meanwhile gets its challenge (201)
  db-vanish   the SQLite file deleted under the server after an enrolment: /health 503
              `store-unavailable` within 2 s, none of 10 enrolments after it acknowledged, and the
              restart on that path logs that it created a new, empty database
  head-flood  4,000 heads without a body from 127.0.0.2 (reopened <= 1,000/s) and 8 bodies of 16 MiB - 1 byte sent at
              once then stalled from 127.0.0.3, all reopened when answered, for 12 s: 4 clients of
              127.0.0.1 (a new connection per request) get >= 95 % of their verifications answered
              200 at >= 50 % of their unattacked throughput, and VmHWM grows <= 200 MB
              (scripts/reliability/fairness.py)
  slow-bodies 64 addresses x 16 bodies at 8.5 KiB/s (just above the minimum rate), reopened when
              answered, for 12 s: the 4 clients keep >= 50 % of their unattacked throughput
  overload    (not in the default set: long, and its figures want a release build) hey with
              8 clients for 20 s (the peak), then 200 clients for 60 s: 0 responses other than
              200/503, successful verifications/s at 200 clients >= 90% of the rate at 8, peak
              RSS <= 300 MB; meanwhile 4 clients enrol new subjects one after another, and
              every enrolment is accepted (none refused by the flood)

  scripts/reliability/reliability.py                      # all but overload
  scripts/reliability/reliability.py stalled-heads db-down
  scripts/reliability/reliability.py trickle --bin /path/to/another/facegate
  scripts/reliability/reliability.py overload --bin target/release/facegate
  scripts/reliability/reliability.py overload --bin target/release/facegate --serve-flag=--admission-wait-ms=0
Needs the IMM photos at $FACEGATE_SHARED/data/imm (default ../shared); `overload` needs hey;
`db-down` needs PostgreSQL's server binaries (apt-get install postgresql).
"""

import argparse
import glob
import http.client
import json
import os
import pwd
import re
import secrets
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SHARED = os.environ.get("FACEGATE_SHARED", os.path.join(ROOT, "..", "shared"))
IMM = os.path.join(SHARED, "data", "imm")


def serve_command(binary, database_url, *flags):
    return [binary, "serve", "--bind", "127.0.0.1:0", "--database", database_url, "--models", os.path.join(ROOT, "models"), *flags]


def serve_env():
    """The environment of the server: this one, without the settings a scenario gives as flags."""
    env = dict(os.environ, NO_COLOR="1", RUST_LOG="warn,facegate::cli::serve=info")
    for name in ("FACEGATE_API_KEYS", "FACEGATE_API_KEYS_FILE", "FACEGATE_TEMPLATE_KEY_FILE", "FACEGATE_DATABASE_URL",
                 "FACEGATE_DATABASE_PASSWORD_FILE"):
        env.pop(name, None)
    return env


class Server:
    """`facegate serve` on a free loopback port with a fresh (or given) SQLite database, or the
    database at `url`."""

    def __init__(self, binary, workdir, *flags, database=None, url=None):
        self.workdir = workdir
        self.database = database or os.path.join(workdir, f"facegate-{uuid.uuid4().hex[:8]}.db")
        self.log_path = os.path.join(workdir, f"server-{uuid.uuid4().hex[:8]}.log")
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            serve_command(binary, url or f"sqlite://{self.database}", *flags),
            stdout=self.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=serve_env(), cwd=ROOT,
        )
        self.port = None
        for _ in range(600):
            with open(self.log_path) as f:
                m = re.search(r"listening on http://127\.0\.0\.1:(\d+)", f.read())
            if m:
                self.port = int(m.group(1))
                break
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        if self.port is None:
            raise RuntimeError("the server did not start:\n" + open(self.log_path).read())

    def peak_rss_mb(self):
        return self._status_mb("VmHWM")

    def reset_peak_rss(self):
        """Sets VmHWM back to the current RSS (Linux: 5 to /proc/<pid>/clear_refs), so that a
        peak measured next is the one the load makes, not start-up's (loading the models)."""
        with open(f"/proc/{self.proc.pid}/clear_refs", "w") as f:
            f.write("5")

    def rss_mb(self):
        return self._status_mb("VmRSS")

    def _status_mb(self, field):
        with open(f"/proc/{self.proc.pid}/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024
        return float("nan")

    def connect(self, source="127.0.0.1"):
        """A connection to the server from the loopback address `source` (any of 127.0.0.0/8)."""
        return socket.create_connection(("127.0.0.1", self.port), timeout=30, source_address=(source, 0))

    def request(self, method, path, body=None, headers=None, timeout=120, source=None):
        """`method path` on a new connection (from the loopback address `source`, if given)."""
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=timeout, source_address=(source, 0) if source else None)
        try:
            conn.request(method, path, body=body, headers=headers or {})
            response = conn.getresponse()
            return response.status, response.read()
        finally:
            conn.close()

    def stop(self, sig=signal.SIGTERM):
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=60)
        self.log.close()


def multipart(fields, boundary="facegate-reliability"):
    """A multipart/form-data body of (name, filename or None, bytes) fields."""
    out = bytearray()
    for name, filename, data in fields:
        out += f"--{boundary}\r\n".encode()
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"Content-Disposition: {disposition}\r\n\r\n".encode()
        out += data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"


def photo(name):
    with open(os.path.join(IMM, name), "rb") as f:
        return f.read()


class CloseWatcher:
    """Records when the peer closes each registered socket, watching all of them at once (epoll).

    Sockets checked one after another could be counted late because the checker itself was slow
    (descheduled on a busy machine) though the server had closed them in time; watching them all
    from the moment they are opened keeps the observed close time within a few milliseconds of the
    real one. The observed time is an upper bound: a stall here can only make the server look later.
    """

    def __init__(self):
        self.selector = selectors.DefaultSelector()
        self.lock = threading.Lock()
        self.closed_at = {}
        self.done = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def add(self, sock):
        with self.lock:
            self.selector.register(sock, selectors.EVENT_READ)

    def _run(self):
        while not self.done:
            with self.lock:
                events = self.selector.select(timeout=0) if self.selector.get_map() else []
            if not events:
                time.sleep(0.002)
                continue
            now = time.monotonic()
            for key, _ in events:
                sock = key.fileobj
                try:
                    data = sock.recv(4096)
                except (ConnectionResetError, BrokenPipeError):
                    data = b""
                except BlockingIOError:
                    continue
                if data == b"":
                    with self.lock:
                        self.closed_at[sock.fileno()] = now
                        self.selector.unregister(sock)

    def stop(self):
        self.done = True
        self.thread.join()
        self.selector.close()


def slowloris(args, work):
    header_timeout = 3.0
    n = 1000
    server = Server(args.bin, work, "--header-timeout-secs", str(header_timeout), "--max-connections", "1024")
    watcher = CloseWatcher()
    try:
        start = time.monotonic()
        socks = []
        for _ in range(n):
            s = server.connect()
            s.sendall(b"GET / HTTP/1.1\r\nX: ")
            s.setblocking(False)
            socks.append((s, s.fileno(), time.monotonic()))
            watcher.add(s)
        opened = time.monotonic() - start
        # Each must be closed within the timeout (+1 s) of its opening; wait a little past the last
        # deadline so that a late close is still measured (and reported) rather than just missed.
        last_deadline = socks[-1][2] + header_timeout + 1.0
        while time.monotonic() < last_deadline + 2.0 and len(watcher.closed_at) < n:
            time.sleep(0.05)
        watcher.stop()
        open_for = [watcher.closed_at[fd] - at if fd in watcher.closed_at else None for _, fd, at in socks]
        late = sum(1 for t in open_for if t is None or t > header_timeout + 1.0)
        never = sum(1 for t in open_for if t is None)
        longest = max((t for t in open_for if t is not None), default=0.0)
        for s, _, _ in socks:
            s.close()
        status, _ = server.request("GET", "/health")
        ok = late == 0 and status == 200
        return ok, (f"{n} half-open connections (opened in {opened:.1f} s), header timeout {header_timeout:.0f} s: "
                    f"{n - late} closed within it + 1 s of their opening, {late} not ({never} still open "
                    f"2 s after the last deadline); the longest open {longest:.2f} s; /health then {status}")
    finally:
        server.stop()


def read_head(sock, timeout):
    """The status line and whether the answer names the `request-timeout` problem type."""
    sock.settimeout(timeout)
    data = b""
    try:
        while b"}" not in data:
            chunk = sock.recv(4096)
            if not chunk:
                break
            data += chunk
    except (socket.timeout, ConnectionResetError):
        pass
    return data.split(b"\r\n", 1)[0].decode(errors="replace"), data


def slow_body(args, work):
    body_timeout = 3.0
    n, declared, sent = 60, 15_000_000, 1_000_000
    server = Server(args.bin, work, "--body-timeout-secs", str(body_timeout))
    try:
        socks = []
        for _ in range(n):
            s = server.connect()
            s.settimeout(5)
            started = time.monotonic()
            try:
                s.sendall(b"POST /verify HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                          + f"Content-Length: {declared}\r\n\r\n".encode()
                          + b'--b\r\nContent-Disposition: form-data; name="image"; filename="p.jpg"\r\n\r\n' + b"\xff" * sent)
            except OSError:
                pass  # refused before its body: the server stopped reading
            socks.append((s, started))
        statuses = {}
        late = 0
        for s, started in socks:
            line, data = read_head(s, body_timeout + 5)
            kind = line.split(" ")[1] if line.startswith("HTTP/1.1") else "none"
            if kind == "408" and b"request-timeout" not in data:
                kind = "408-untyped"
            statuses[kind] = statuses.get(kind, 0) + 1
            late += time.monotonic() - started > body_timeout + 1.0
            s.close()
        rss = server.peak_rss_mb()
        ok = set(statuses) <= {"408", "503"} and statuses.get("408", 0) > 0 and late == 0 and rss <= 300
        return ok, (f"{n} uploads declaring 15 MB that stall after 1 MB, body timeout {body_timeout:.0f} s: answers {statuses} "
                    f"(408 request-timeout, or 503 beyond the body-memory budget), {late} later than the timeout + 1 s; peak RSS {rss:.0f} MB")
    finally:
        server.stop()


def kill9(args, work):
    rounds, clients, storm_s = 3, 8, args.storm_secs
    photos = [photo(name) for name in sorted(f for f in os.listdir(IMM) if f.endswith(".jpg"))[:8]]
    lost_total, acknowledged_total = 0, 0
    details = []
    database = os.path.join(work, "kill9.db")
    for round_ in range(rounds):
        server = Server(args.bin, work, database=database)
        acknowledged = []
        lock = threading.Lock()
        stop = threading.Event()

        def storm(client):
            i = 0
            while not stop.is_set():
                subject = f"r{round_}-c{client}-{i}"
                body, ctype = multipart([("subject", None, subject.encode()), ("image", "p.jpg", photos[(client + i) % len(photos)])])
                try:
                    status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype}, timeout=30)
                except OSError:
                    return
                if status == 201:
                    with lock:
                        acknowledged.append(subject)
                i += 1

        threads = [threading.Thread(target=storm, args=(c,)) for c in range(clients)]
        for t in threads:
            t.start()
        time.sleep(storm_s)
        server.proc.send_signal(signal.SIGKILL)
        server.proc.wait()
        stop.set()
        for t in threads:
            t.join()
        server.log.close()
        restarted = Server(args.bin, work, database=database)
        try:
            lost = [s for s in acknowledged if restarted.request("GET", f"/subjects/{s}")[0] != 200]
        finally:
            restarted.stop()
        lost_total += len(lost)
        acknowledged_total += len(acknowledged)
        details.append(f"{len(acknowledged)} acknowledged, {len(lost)} lost")
    return lost_total == 0 and acknowledged_total > 0, f"kill -9 during an enrolment storm ({clients} clients, {storm_s:.0f} s) x {rounds}: " + "; ".join(details)


def sigterm(args, work):
    grace = 3.0
    server = Server(args.bin, work, "--shutdown-grace-secs", str(grace), "--header-timeout-secs", "30", "--body-timeout-secs", "25")
    idle = server.connect()
    idle.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
    idle.settimeout(10)
    first = idle.recv(4096)
    stalled = server.connect()
    stalled.sendall(b"POST /enroll HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                    b"Content-Length: 1000000\r\n\r\n--b\r\n")
    time.sleep(0.5)
    start = time.monotonic()
    server.proc.send_signal(signal.SIGTERM)
    try:
        code = server.proc.wait(timeout=grace + 10)
    except subprocess.TimeoutExpired:
        code = None
        server.proc.kill()
    elapsed = time.monotonic() - start
    server.log.close()
    idle.close()
    stalled.close()
    ok = first.startswith(b"HTTP/1.1 200") and code == 0 and elapsed <= grace + 1.0
    return ok, f"SIGTERM with an idle keep-alive connection and a stalled upload, grace {grace:.0f} s: exited {code} after {elapsed:.2f} s"


def hey(url, clients, seconds, body_path, ctype):
    out = subprocess.run(["hey", "-z", f"{seconds}s", "-c", str(clients), "-m", "POST", "-T", ctype, "-D", body_path, "-t", "60", url],
                         capture_output=True, text=True, check=True).stdout
    codes = {int(c): int(n) for c, n in re.findall(r"\[(\d{3})\]\s+(\d+) responses", out)}
    errors = re.search(r"Error distribution:(.*)", out, re.S)
    return codes, (errors.group(1).strip() if errors else "")


# Clients enrolling during the overload scenario's verification flood.
ENROL_CLIENTS = 4


def overload(args, work):
    if shutil.which("hey") is None:
        return False, "hey is missing"
    server = Server(args.bin, work, *args.serve_flag)
    try:
        body, ctype = multipart([("subject", None, b"loadtest"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, status
        probe, ctype = multipart([("subject", None, b"loadtest"), ("image", "p.jpg", photo("01-2m.jpg"))])
        body_path = os.path.join(work, "probe.bin")
        with open(body_path, "wb") as f:
            f.write(probe)
        url = f"http://127.0.0.1:{server.port}/verify"
        peak_codes, _ = hey(url, 8, args.peak_secs, body_path, ctype)
        peak = peak_codes.get(200, 0) / args.peak_secs
        # Enrolments during the verification flood: ENROL_CLIENTS clients enrol one new subject
        # after another; each must be accepted (201), not starved by the flood (503).
        enrolments = {"201": 0, "503": 0, "other": 0}
        latencies = []
        lock = threading.Lock()
        flooding = threading.Event()
        flooding.set()
        enrol_photo = photo("01-1m.jpg")

        def enrol(client):
            i = 0
            while flooding.is_set():
                body, ctype = multipart([("subject", None, f"flood-{client}-{i}".encode()), ("image", "p.jpg", enrol_photo)])
                start = time.monotonic()
                try:
                    status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype}, timeout=60)
                except OSError:
                    status = None
                with lock:
                    enrolments[str(status) if status in (201, 503) else "other"] += 1
                    if status == 201:
                        latencies.append(time.monotonic() - start)
                i += 1

        enrollers = [threading.Thread(target=enrol, args=(c,)) for c in range(ENROL_CLIENTS)]
        for t in enrollers:
            t.start()
        codes, errors = hey(url, 200, args.overload_secs, body_path, ctype)
        flooding.clear()
        for t in enrollers:
            t.join()
        rate = codes.get(200, 0) / args.overload_secs
        others = sum(n for c, n in codes.items() if c not in (200, 503))
        rss = server.peak_rss_mb()
        latencies.sort()
        enrol_p50 = latencies[len(latencies) // 2] if latencies else float("nan")
        enrol_ok = enrolments["201"] > 0 and enrolments["503"] == 0 and enrolments["other"] == 0
        ok = others == 0 and not errors and rate >= 0.9 * peak and rss <= 300 and enrol_ok
        return ok, (f"8 clients {args.peak_secs} s: {peak:.1f} verifications/s ({peak_codes}); 200 clients {args.overload_secs} s: "
                    f"{rate:.1f}/s = {rate / peak if peak else 0:.2f} of the peak, responses {codes}, other statuses {others}, "
                    f"client errors {errors or 'none'}; peak RSS {rss:.0f} MB; meanwhile {ENROL_CLIENTS} enrolling clients: "
                    f"{enrolments['201']} enrolled, {enrolments['503']} refused, {enrolments['other']} other, p50 {enrol_p50:.2f} s")
    finally:
        server.stop()


def answered_status(sock, received):
    """Read what the non-blocking `sock` has after `received`: (the response's status code, or
    "closed" when the peer closed without one; None while the status line has not arrived yet,
    all that was read so far)."""
    try:
        chunk = sock.recv(4096)
    except BlockingIOError:
        return None, received
    except OSError:
        chunk = b""
    received += chunk
    if chunk and b"\r\n" not in received:
        return None, received
    line = received.split(b"\r\n", 1)[0].decode(errors="replace")
    return (line.split(" ")[1] if line.startswith("HTTP/1.1 ") else "closed"), received


def problem_slug(data):
    """The last segment of a problem+json answer's type URI ("" when the body is not one)."""
    try:
        return str(json.loads(data).get("type", "")).rsplit("/", 1)[-1]
    except (ValueError, AttributeError):
        return ""


def problem_detail(data):
    """The `detail` of a problem+json answer ("" when the body is not one)."""
    try:
        return str(json.loads(data).get("detail", ""))
    except (ValueError, AttributeError):
        return ""


# The default body limit (16 MiB), and the routes the 125,000-byte stalled heads cycle through.
BODY_LIMIT = 16 << 20
STALLED_ROUTES = ["/verify", "/enroll", "/identify", "/analyze"]


def stalled_heads(args, work):
    attack_s, legit_n, legit_clients, pace_s = 12.0, 48, 4, 1.0
    heads = ([("over-limit", "/verify", BODY_LIMIT + 1)] * 8 + [("15 MiB", "/verify", 15 << 20)] * 8
             + [("125 kB", STALLED_ROUTES[i % len(STALLED_ROUTES)], 125_000) for i in range(70)])
    server = Server(args.bin, work, "--workers", "2", "--queue", "4", "--enrol-queue", "2")
    selector = selectors.DefaultSelector()
    answers = {}  # (kind, status or "closed") -> [seconds from the head to the answer]
    opened = [0]
    attacking = threading.Event()
    attacking.set()

    def open_head(kind, route, length):
        # From another address than the legitimate clients': an address's own stalled heads take
        # its own places (--max-uploads-per-address counts heads waiting for their bodies).
        s = server.connect("127.0.0.2")
        s.sendall(f"POST {route} HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                  f"Content-Length: {length}\r\n\r\n".encode())
        s.setblocking(False)
        selector.register(s, selectors.EVENT_READ, [kind, route, length, time.monotonic(), b""])
        opened[0] += 1

    def attack():
        # The heads stay open until the server answers or closes them; then they are opened again
        # (the over-limit ones excepted: they are answered at once, nothing is left to hold), for
        # at most attack_s and 2,000 heads in all.
        deadline = time.monotonic() + attack_s
        while attacking.is_set() and time.monotonic() < deadline + 10:
            for key, _ in selector.select(timeout=0.05):
                s, state = key.fileobj, key.data
                status, state[4] = answered_status(s, state[4])
                if status is None:
                    continue
                answers.setdefault((state[0], status), []).append(time.monotonic() - state[3])
                selector.unregister(s)
                s.close()
                if state[0] != "over-limit" and attacking.is_set() and time.monotonic() < deadline and opened[0] < 2000:
                    try:
                        open_head(*state[:3])
                    except OSError as e:
                        answers.setdefault((state[0], f"not reopened: {type(e).__name__}"), []).append(0.0)

    legit = {}
    mismatches = [0]
    lock = threading.Lock()
    attacker = None
    try:
        body, ctype = multipart([("subject", None, b"imm01"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, f"enrolling IMM 01-1m: {status}"
        probe, ctype = verify_multipart("imm01", "01-2m.jpg")
        for kind, route, length in heads:
            open_head(kind, route, length)
        attacker = threading.Thread(target=attack)
        attacker.start()
        start = time.monotonic()

        def client(c):
            # Verification i of this client starts at start + i * pace_s (legit_n / legit_clients
            # each), so that they cover the whole attack, heads timed out and opened again included.
            for i in range(legit_n // legit_clients):
                wait = start + i * pace_s - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                if time.monotonic() - start > attack_s + 10:
                    status = "not sent"
                else:
                    try:
                        status, data = server.request("POST", "/verify", probe, {"Content-Type": ctype}, timeout=30)
                        if status == 200 and json.loads(data).get("match") is not True:
                            with lock:
                                mismatches[0] += 1
                    except OSError as e:
                        status = type(e).__name__
                with lock:
                    legit[status] = legit.get(status, 0) + 1

        clients = [threading.Thread(target=client, args=(c,)) for c in range(legit_clients)]
        for t in clients:
            t.start()
        for t in clients:
            t.join()
        legit_s = time.monotonic() - start
        attacking.clear()
        attacker.join()
        health, _ = server.request("GET", "/health")
    finally:
        attacking.clear()
        if attacker is not None:
            attacker.join()
        for key in list(selector.get_map().values()):
            key.fileobj.close()
        selector.close()
        server.stop()
    ok_200 = legit.get(200, 0)
    over = answers.get(("over-limit", "413"), [])
    over_slowest = max(over, default=float("nan"))
    counts = {f"{kind} {status}": len(times) for (kind, status), times in sorted(answers.items())}
    stalled_408 = [t for (kind, status), times in answers.items() if kind != "over-limit" and status == "408" for t in times]
    ok = (ok_200 >= 0.95 * legit_n and mismatches[0] == 0 and len(over) == 8 and over_slowest <= 1.0 and health == 200)
    return ok, (f"{len(heads)} stalled heads (8 over the limit, 8 x 15 MiB, 70 x 125 kB over {', '.join(STALLED_ROUTES)}), "
                f"opened again when answered, {opened[0]} in all over {legit_s:.0f} s, --workers 2 --queue 4 --enrol-queue 2: "
                f"{ok_200}/{legit_n} legitimate verifications answered 200 ({mismatches[0]} of them no match; all answers {legit}); "
                f"over-limit heads: {len(over)}/8 answered 413, the slowest in {over_slowest:.2f} s; the stalled heads' answers {counts}, "
                f"408 after {min(stalled_408, default=float('nan')):.1f}-{max(stalled_408, default=float('nan')):.1f} s; /health then {health}")


def json_flood(args, work):
    n = 3_000_000
    # `"AA"` (5 bytes with its comma) x 3,000,000: 15.0 MB, under the 16 MiB body limit.
    body = b'{"subject":"a","images":[' + b'"AA",' * (n - 1) + b'"AA"]}'
    assert len(body) < BODY_LIMIT
    headers = {"Content-Type": "application/json"}
    server = Server(args.bin, work)
    answers = {}
    lock = threading.Lock()
    try:
        server.reset_peak_rss()
        rss_before, hwm_before = server.rss_mb(), server.peak_rss_mb()

        def flood(source="127.0.0.1"):
            try:
                status, data = server.request("POST", "/enroll", body, headers, timeout=60, source=source)
                answer = f"{status} {problem_slug(data)}"
            except OSError as e:
                answer = type(e).__name__
            with lock:
                answers[answer] = answers.get(answer, 0) + 1

        flood()
        hwm_one = server.peak_rss_mb()
        health_latencies = []
        flooding = threading.Event()
        flooding.set()

        def health():
            # /health every 50 ms while the concurrent floods are in flight (at most 600 requests).
            for _ in range(600):
                if not flooding.is_set():
                    return
                started = time.monotonic()
                try:
                    status, _ = server.request("GET", "/health", timeout=10)
                except OSError:
                    status = None
                health_latencies.append((status, time.monotonic() - started))
                time.sleep(0.05)

        # From four addresses: one address's bodies hold at most its share of the body budget
        # (--max-buffered-per-address-mb, two such bodies), and this measures the parse.
        floods = [threading.Thread(target=flood, args=(f"127.0.0.{1 + i}",)) for i in range(4)]
        prober = threading.Thread(target=health)
        prober.start()
        for t in floods:
            t.start()
        for t in floods:
            t.join()
        flooding.clear()
        prober.join()
        hwm_after = server.peak_rss_mb()
    finally:
        server.stop()
    growth_one, growth = hwm_one - rss_before, hwm_after - rss_before
    slowest_health = max((t for _, t in health_latencies), default=float("nan"))
    health_ok = bool(health_latencies) and all(s == 200 for s, _ in health_latencies) and slowest_health <= 1.0
    # The target is for one body: its parse may grow the process by at most 50 MB. Four at once
    # also hold their four bodies (counted by the body budget), so they may add those.
    held = 4 * len(body) / 1e6
    ok = answers == {"400 malformed-request": 5} and growth_one <= 50 and growth <= 50 + held and health_ok
    return ok, (f"a {len(body) / 1e6:.1f} MB JSON body of {n:,} photos (\"AA\") to /enroll, once then 4 at once: answers {answers}; "
                f"RSS before {rss_before:.0f} MB (peak {hwm_before:.0f} MB), peak after the single one {hwm_one:.0f} MB "
                f"(+{growth_one:.0f} MB), after the 4 at once {hwm_after:.0f} MB (+{growth:.0f} MB); "
                f"{len(health_latencies)} /health meanwhile, statuses {sorted(set(s for s, _ in health_latencies), key=str)}, "
                f"the slowest {slowest_health:.2f} s")


class Trickles:
    """`n` connections from the loopback address `source`, each a `POST route` head declaring
    `length` bytes followed by one byte a second, opened again once the server answers (or closes)
    them, until stopped."""

    def __init__(self, server, route, length, n, source="127.0.0.1"):
        self.server, self.n, self.source = server, n, source
        self.head = (f"POST {route} HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                     f"Content-Length: {length}\r\n\r\n").encode()
        self.selector = selectors.DefaultSelector()
        self.answers = {}  # status (or "closed") -> [seconds from the head to the answer]
        self.opened = 0
        self.running = threading.Event()
        self.running.set()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _open(self):
        s = self.server.connect(self.source)
        s.sendall(self.head + b"-")
        s.setblocking(False)
        self.selector.register(s, selectors.EVENT_READ, [time.monotonic(), b""])
        self.opened += 1

    def _answered(self, key):
        s, state = key.fileobj, key.data
        status, state[1] = answered_status(s, state[1])
        if status is None:
            return
        self.answers.setdefault(status, []).append(time.monotonic() - state[0])
        self.selector.unregister(s)
        s.close()
        if self.running.is_set():
            self._open()

    def _run(self):
        for _ in range(self.n):
            self._open()
        tick = time.monotonic() + 1.0
        while self.running.is_set():
            for key, _ in self.selector.select(timeout=max(0.0, min(0.1, tick - time.monotonic()))):
                self._answered(key)
            if time.monotonic() >= tick:
                tick += 1.0
                for key in list(self.selector.get_map().values()):
                    try:
                        key.fileobj.send(b"-")
                    except OSError:
                        pass

    def start(self):
        self.thread.start()

    def stop(self):
        self.running.clear()
        self.thread.join()
        for key in list(self.selector.get_map().values()):
            key.fileobj.close()
        self.selector.close()

    def summary(self):
        parts = [f"{status} x{len(times)} after {min(times):.1f}-{max(times):.1f} s" for status, times in sorted(self.answers.items())]
        return f"{self.opened} heads in all, answered: {', '.join(parts) or 'none'}"


def trickle(args, work):
    runs = [trickle_run(args, work, "/verify", 8, BODY_LIMIT, "127.0.0.1"), trickle_run(args, work, "/enroll", 8, BODY_LIMIT, "127.0.0.1"),
            trickle_run(args, work, "/verify", 66, 125_000, "127.0.0.2")]
    return all(ok for ok, _ in runs), "; ".join(line for _, line in runs)


def trickle_run(args, work, route, n, length, source):
    attack_s = 12.0
    server = Server(args.bin, work)
    trickles = None
    tally = {"verify": {}, "enroll": {}}
    mismatches = 0
    try:
        body, ctype = multipart([("subject", None, b"imm01"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, f"enrolling IMM 01-1m: {status}"
        probe, ctype = verify_multipart("imm01", "01-2m.jpg")
        enrol_photo = photo("01-1m.jpg")
        trickles = Trickles(server, route, length, n, source)
        trickles.start()
        time.sleep(1.5)  # the trickles have begun their bodies
        start = time.monotonic()
        i = 0
        while time.monotonic() - start < attack_s:
            # With the trickles on /enroll, every other request is an enrolment of a new subject.
            kind = "enroll" if route == "/enroll" and i % 2 else "verify"
            if kind == "verify":
                request = ("POST", "/verify", probe, {"Content-Type": ctype})
            else:
                enrolment, enrol_type = multipart([("subject", None, f"new-{i}".encode()), ("image", "p.jpg", enrol_photo)])
                request = ("POST", "/enroll", enrolment, {"Content-Type": enrol_type})
            try:
                status, data = server.request(*request, timeout=30)
                mismatches += kind == "verify" and status == 200 and json.loads(data).get("match") is not True
                answer = f"{status} {problem_slug(data)}".strip()
            except OSError as e:
                status, answer = None, type(e).__name__
            tally[kind][answer] = tally[kind].get(answer, 0) + 1
            i += 1
            if status == 503:
                time.sleep(1.0)  # the Retry-After of every 503
        trickles.stop()
        trickles_done = trickles.summary()
        trickles = None
        health, _ = server.request("GET", "/health")
    finally:
        if trickles is not None:
            trickles.stop()
        server.stop()

    def share(kind, ok_status):
        total = sum(tally[kind].values())
        return tally[kind].get(ok_status, 0), total

    verified, verifications = share("verify", "200")
    enrolled, enrolments = share("enroll", "201")
    ok = (verifications >= 10 and verified >= 0.95 * verifications and mismatches == 0 and health == 200
          and (route != "/enroll" or (enrolments >= 5 and enrolled >= 0.95 * enrolments)))
    legit = f"{verified}/{verifications} verifications answered 200 ({mismatches} no match; {tally['verify']})"
    if route == "/enroll":
        legit += f", {enrolled}/{enrolments} enrolments answered 201 ({tally['enroll']})"
    return ok, (f"{n} trickles from {source} on {route} (a head declaring {length:,} bytes, then 1 byte/s, opened again when "
                f"answered) for {attack_s:.0f} s: {legit}; trickles: {trickles_done}; /health then {health}")


def part_flood(args, work):
    n = 150_000
    part = b'--b\r\nContent-Disposition: form-data; name="image"; filename="p.jpg"\r\n\r\nx\r\n'
    subject = b'--b\r\nContent-Disposition: form-data; name="subject"\r\n\r\nmany\r\n'
    body = subject + part * n + b"--b--\r\n"
    assert len(body) < BODY_LIMIT
    server = Server(args.bin, work)
    try:
        server.reset_peak_rss()
        rss_before = server.rss_mb()
        started = time.monotonic()
        try:
            status, data = server.request("POST", "/enroll", body, {"Content-Type": "multipart/form-data; boundary=b"}, timeout=60)
            answer, detail = f"{status} {problem_slug(data)}", problem_detail(data)
        except OSError as e:
            status, answer, detail = None, type(e).__name__, ""
        took = time.monotonic() - started
        growth = server.peak_rss_mb() - rss_before
        health, _ = server.request("GET", "/health")
    finally:
        server.stop()
    ok = status is not None and 400 <= status < 500 and growth <= 50 and health == 200
    return ok, (f"a {len(body) / 1e6:.1f} MB multipart body of {n:,} one-byte image parts to /enroll: answered {answer} "
                f"(\"{detail}\") in {took:.2f} s; peak RSS growth +{growth:.0f} MB (RSS before {rss_before:.0f} MB); "
                f"/health then {health}")


def run_to_exit(binary, work, database, *flags, timeout=30.0):
    """Run `facegate serve` expecting it to refuse to start: (exit status, or None if it was still
    running after `timeout` or once it printed its "listening on" line (then it is killed at once),
    seconds, whether it printed that line, its last log line)."""
    log_path = os.path.join(work, f"refused-{uuid.uuid4().hex[:8]}.log")
    started = time.monotonic()
    code = None
    with open(log_path, "w") as log:
        proc = subprocess.Popen(serve_command(binary, f"sqlite://{database}", *flags), stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=serve_env(), cwd=ROOT)
        try:
            while time.monotonic() - started < timeout:
                code = proc.poll()
                with open(log_path) as f:
                    if code is not None or "listening on" in f.read():
                        break
                time.sleep(0.05)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
    elapsed = time.monotonic() - started
    with open(log_path) as f:
        text = f.read()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return code, elapsed, "listening on" in text, (lines[-1] if lines else "")


def fail_closed(args, work):
    comments = os.path.join(work, "keys-comments-only")
    with open(comments, "w") as f:
        f.write("# the API keys of this deployment\n\n# (none yet)\n")
    k1, k2 = os.path.join(work, "template-key-1"), os.path.join(work, "template-key-2")
    for path in (k1, k2):
        with open(path, "w") as f:
            f.write(secrets.token_hex(32) + "\n")
    sealed = os.path.join(work, "sealed.db")
    server = Server(args.bin, work, "--template-key-file", k1, database=sealed)
    try:
        body, ctype = multipart([("subject", None, b"sealed"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, f"enrolling under the first template key: {status}"
    finally:
        server.stop()
    cases = [
        ("--api-keys ',,'", os.path.join(work, f"open-{uuid.uuid4().hex[:8]}.db"), ["--api-keys", ",,"]),
        ("--api-keys-file of comments", os.path.join(work, f"open-{uuid.uuid4().hex[:8]}.db"), ["--api-keys-file", comments]),
        ("sealed database, no template key", sealed, []),
        ("sealed database, another template key", sealed, ["--template-key-file", k2]),
    ]
    results, ok = [], True
    for name, database, flags in cases:
        code, elapsed, listening, last = run_to_exit(args.bin, work, database, *flags)
        refused = code not in (None, 0) and not listening
        ok &= refused
        reason = re.sub(r"\x1b\[[0-9;]*m", "", last).split("error: ", 1)[-1].replace(work + os.sep, "")
        reason = reason if len(reason) <= 100 else reason[:100] + "..."
        results.append(f"{name}: exit {code} after {elapsed:.2f} s, {'printed' if listening else 'no'} \"listening on\""
                       f"{'' if refused else ' (NOT REFUSED)'} (\"{reason}\")")
    # The control: the sealed database still opens with its own key, the subject intact.
    server = Server(args.bin, work, "--template-key-file", k1, database=sealed)
    try:
        control, _ = server.request("GET", "/subjects/sealed")
    finally:
        server.stop()
    ok &= control == 200
    return ok, "; ".join(results) + f"; with the first key again the sealed subject answers {control}"


def postgres_bin_dir():
    """The directory holding `initdb` and `pg_ctl` (and `psql`): on PATH (a symbolic link followed to
    the server's own directory), or Debian's newest versioned one."""
    candidates = os.environ.get("PATH", "").split(os.pathsep)
    candidates += sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda d: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", d)], reverse=True)
    for d in candidates:
        if d and os.path.isfile(os.path.join(d, "initdb")) and os.path.isfile(os.path.join(d, "pg_ctl")):
            real = os.path.dirname(os.path.realpath(os.path.join(d, "initdb")))
            return real if os.path.isfile(os.path.join(real, "pg_ctl")) else d
    return None


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Postgres:
    """A throwaway PostgreSQL cluster on 127.0.0.1 (trust authentication), run as the `postgres`
    user when this script runs as root, in a temporary directory of its own."""

    def __init__(self, bindir):
        self.bindir = bindir
        self.user = "postgres" if os.geteuid() == 0 else None
        self.dir = tempfile.mkdtemp(prefix="facegate-reliability-pg-")
        if self.user:
            entry = pwd.getpwnam(self.user)
            os.chown(self.dir, entry.pw_uid, entry.pw_gid)
        self.data = os.path.join(self.dir, "data")
        self.log = os.path.join(self.dir, "server.log")
        self.port = free_port()

    def run(self, program, *argv, timeout=90):
        command = [os.path.join(self.bindir, program), *argv]
        if self.user:
            command = ["runuser", "-u", self.user, "--", *command]
        out = subprocess.run(command, capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL, cwd=self.dir)
        if out.returncode != 0:
            raise RuntimeError(f"{program} {' '.join(argv)}: exit {out.returncode}: {out.stdout}{out.stderr}")

    def init(self):
        self.run("initdb", "-D", self.data, "-A", "trust", "-U", "postgres", "-E", "UTF8", "--no-sync")

    def start(self):
        options = f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1"
        self.run("pg_ctl", "-D", self.data, "-l", self.log, "-o", options, "-w", "-t", "60", "start")

    def stop_hard(self):
        self.run("pg_ctl", "-D", self.data, "-m", "immediate", "-w", "-t", "30", "stop")

    def url(self, database):
        return f"postgres://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self, name):
        psql = os.path.join(self.bindir, "psql")
        out = subprocess.run([psql if os.path.isfile(psql) else "psql", self.url("postgres"), "-v", "ON_ERROR_STOP=1", "-qc", f"CREATE DATABASE {name}"],
                             capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
        if out.returncode != 0:
            raise RuntimeError(f"CREATE DATABASE {name}: {out.stderr}")

    def destroy(self):
        if os.path.exists(os.path.join(self.data, "postmaster.pid")):
            try:
                self.stop_hard()
            except (RuntimeError, subprocess.TimeoutExpired):
                pass
        shutil.rmtree(self.dir, ignore_errors=True)


def db_down(args, work):
    bindir = postgres_bin_dir()
    why = None
    if bindir is None:
        why = "no initdb/pg_ctl on PATH or under /usr/lib/postgresql/*/bin (apt-get install postgresql)"
    elif os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            why = "running as root and there is no postgres user to run the cluster as"
    if why:
        if os.environ.get("FACEGATE_REQUIRE_POSTGRES", "") not in ("", "0"):
            return False, f"PostgreSQL is required (FACEGATE_REQUIRE_POSTGRES) but unavailable: {why}"
        return None, f"no PostgreSQL server: {why}"
    pg = Postgres(bindir)
    try:
        pg.init()
        pg.start()
        pg.create_database("facegate_reliability")
        # A 4 s request timeout, so that a request stuck on the database is answered 504 within the
        # clients' 5 s (and its enrolment checked), rather than timed out by the client.
        server = Server(args.bin, work, "--timeout-secs", "4", "--body-timeout-secs", "4", url=pg.url("facegate_reliability"))
        try:
            return db_down_run(server, pg)
        finally:
            server.stop()
    finally:
        pg.destroy()


def db_down_run(server, pg):
    up_s, down_s, back_s, client_timeout = 3.0, 10.0, 10.0, 5.0
    names = sorted(f for f in os.listdir(IMM) if f.endswith("-1m.jpg"))[:6]
    enrolled, enrol_photos = [], []
    for name in names:
        subject = "base-" + name.split("-")[0]
        body, ctype = multipart([("subject", None, subject.encode()), ("image", "p.jpg", photo(name))])
        if server.request("POST", "/enroll", body, {"Content-Type": ctype})[0] != 201:
            continue
        enrol_photos.append(photo(name))
        probe, ctype = verify_multipart(subject, name.replace("-1m", "-2m"))
        status, data = server.request("POST", "/verify", probe, {"Content-Type": ctype})
        if status == 200 and json.loads(data)["match"]:
            enrolled.append((subject, name.replace("-1m", "-2m")))
    assert len(enrolled) >= 2, f"only {len(enrolled)} IMM subjects enrolled and verified with their genuine probe"
    probes = {subject: verify_multipart(subject, probe) for subject, probe in enrolled}
    records = []
    lock = threading.Lock()
    stop = threading.Event()

    def call(kind, subject, body, ctype):
        started = time.monotonic()
        record = {"kind": kind, "subject": subject, "start": started, "status": None, "slug": "", "retry_after": None, "match": None}
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=client_timeout)
        try:
            conn.request("POST", f"/{kind}", body=body, headers={"Content-Type": ctype})
            response = conn.getresponse()
            data = response.read()
            record.update(status=response.status, retry_after=response.getheader("Retry-After"), slug=problem_slug(data))
            # A write whose commit the database's death interrupted is answered "may or may not be
            # stored": the client is not told it failed.
            record["unknown"] = response.status == 503 and b"may or may not be stored" in data
            if kind == "verify" and response.status == 200:
                record["match"] = json.loads(data).get("match")
        except (OSError, http.client.HTTPException) as e:
            record["error"] = type(e).__name__
        finally:
            conn.close()
        record["end"] = time.monotonic()
        with lock:
            records.append(record)
        return record["status"] in (200, 201)

    def client(c):
        # Verify an enrolled subject, then enrol a new one (a fresh id for every attempt), over and
        # over; 0.1 s of rest after a refusal; at most 1,000 rounds.
        for i in range(1000):
            if stop.is_set():
                return
            subject, _ = enrolled[(c + i) % len(enrolled)]
            ok = call("verify", subject, *probes[subject])
            body, ctype = multipart([("subject", None, f"dd-{c}-{i}".encode()), ("image", "p.jpg", enrol_photos[(c + i) % len(enrol_photos)])])
            ok &= call("enroll", f"dd-{c}-{i}", body, ctype)
            if not ok:
                time.sleep(0.1)

    clients = [threading.Thread(target=client, args=(c,)) for c in range(2)]
    for t in clients:
        t.start()
    try:
        time.sleep(up_s)
        t_stop = time.monotonic()
        pg.stop_hard()
        t_down = time.monotonic()
        time.sleep(down_s)
        t_start = time.monotonic()
        pg.start()
        t_up = time.monotonic()
        time.sleep(back_s)
    finally:
        stop.set()
        for t in clients:
            t.join()
    # Every enrolment attempt, looked up at the end (a 503 while the circuit is still open is asked again).
    present = {}
    for r in records:
        if r["kind"] != "enroll":
            continue
        for _ in range(20):
            status, _ = server.request("GET", f"/subjects/{r['subject']}", timeout=30)
            if status != 503:
                break
            time.sleep(0.25)
        present[r["subject"]] = status
    return db_down_verdict(records, present, t_stop, t_down, t_start, t_up, up_s, down_s, back_s)


def verify_multipart(subject, name):
    body, ctype = multipart([("subject", None, subject.encode()), ("image", "p.jpg", photo(name))])
    return body, ctype


def db_down_verdict(records, present, t_stop, t_down, t_start, t_up, up_s, down_s, back_s):
    def success(r):
        return (r["kind"] == "verify" and r["status"] == 200 and r["match"] is True) or (r["kind"] == "enroll" and r["status"] == 201)

    def refused(r):
        return r["status"] == 503 and r["slug"] == "store-unavailable" and r["retry_after"] is not None

    before = [r for r in records if r["end"] < t_stop]
    in_flight = [r for r in records if r["start"] < t_stop <= r["end"]]
    down = [r for r in records if t_stop <= r["start"] < t_up]
    back = [r for r in records if r["start"] >= t_up]
    # While the database is down (from the stop until it answers again), every request is answered
    # within 2 s: those in flight at the stop counted from the stop.
    waited = {id(r): r["end"] - max(r["start"], t_stop) for r in in_flight + down}
    down_bad = [r for r in in_flight + down if waited[id(r)] > 2.0 or not (refused(r) or success(r))]
    down_slowest = max(waited.values(), default=float("nan"))
    recovered = {kind: min((r["end"] - t_up for r in back if r["kind"] == kind and success(r)), default=None) for kind in ("verify", "enroll")}
    late_failures = [r for r in back if r["start"] >= t_up + 5.0 and not success(r)]
    wrong = [r for r in records if r["kind"] == "verify" and r["status"] == 200 and r["match"] is not True]
    enrolments = [r for r in records if r["kind"] == "enroll"]
    acknowledged = [r for r in enrolments if r["status"] == 201]
    lost = [r for r in acknowledged if present.get(r["subject"]) != 200]
    refusals = [r for r in enrolments if r["status"] in (503, 504) and not r.get("unknown")]
    committed = [r for r in refusals if present.get(r["subject"]) == 200]
    unknown = [r for r in enrolments if r.get("unknown")]
    unknown_present = sum(present.get(r["subject"]) == 200 for r in unknown)
    unanswered = [r for r in enrolments if r["status"] is None]
    unanswered_present = sum(present.get(r["subject"]) == 200 for r in unanswered)

    def tally(rs):
        out = {}
        for r in rs:
            key = f"{r['kind']} {r['status'] or r.get('error')}{' ' + r['slug'] if r['slug'] else ''}"
            out[key] = out.get(key, 0) + 1
        return dict(sorted(out.items()))

    ok = (all(success(r) for r in before) and not down_bad and all(v is not None and v <= 5.0 for v in recovered.values())
          and not late_failures and not wrong and not lost and not committed and acknowledged)

    def describe(r):
        answer = f"{r['status']}{' ' + r['slug'] if r['slug'] else ''}" if r["status"] else r.get("error")
        return (f"{r['kind']} {answer}{'' if r['retry_after'] or r['status'] != 503 else ' without Retry-After'} "
                f"at {r['start'] - t_stop:+.1f} s of the stop, in {r['end'] - r['start']:.2f} s")

    def fmt(v):
        return "never" if v is None else f"{v:.2f} s"

    return ok, (f"2 clients verifying and enrolling; PostgreSQL up {up_s:.0f} s, stopped hard (pg_ctl stop -m immediate, {t_down - t_stop:.1f} s), "
                f"down {down_s:.0f} s, started again ({t_up - t_start:.1f} s), up {back_s:.0f} s: before {tally(before)}; in flight at the stop "
                f"{tally(in_flight)}; while down {tally(down)}, the slowest {down_slowest:.2f} s; {len(down_bad)} outside the target "
                f"(answered within 2 s: 503 store-unavailable with Retry-After, or success){': ' if down_bad else ''}"
                f"{', '.join(describe(r) for r in down_bad[:6])}; after the restart the first verification "
                f"succeeded after {fmt(recovered['verify'])}, the first enrolment after {fmt(recovered['enroll'])}, answers {tally(back)}, "
                f"{len(late_failures)} failed from 5 s on; {len(wrong)} wrong answers; {len(acknowledged)} enrolments acknowledged, "
                f"{len(lost)} lost; {len(refusals)} refused (503/504), {len(committed)} of them committed anyway; "
                f"{len(unknown)} answered outcome unknown (commit cut by the stop), {unknown_present} of them present; "
                f"{len(unanswered)} unanswered (client timeout or error), {unanswered_present} of those present")


def duplicates(args, work):
    import duplicates as scenario  # beside this script (scripts/reliability/duplicates.py)

    return scenario.duplicates(args, work, Server, SHARED, os.path.join(ROOT, "models"))


def head_flood(args, work):
    import fairness  # beside this script (scripts/reliability/fairness.py)

    return fairness.head_flood(args, work, Server, multipart, photo, verify_multipart)


def slow_bodies(args, work):
    import fairness

    return fairness.slow_bodies(args, work, Server, multipart, photo, verify_multipart)


def secrets_scenario(args, work):
    """A start-up that fails on an unreachable PostgreSQL whose password is in the URL, or in
    --database-password-file: no output of it may hold the password, in either log format."""
    password = "s3cret" + secrets.token_hex(4)
    password_file = os.path.join(work, "db-password")
    with open(password_file, "w") as f:
        f.write(password + "\n")
    port = free_port()
    cases = [
        ("serve, text, password in the URL", ["serve", "--bind", "127.0.0.1:0", "--database", f"postgres://u:{password}@127.0.0.1:{port}/db"]),
        ("serve, json, password in the URL",
         ["serve", "--bind", "127.0.0.1:0", "--log-format", "json", "--database", f"postgres://u:{password}@127.0.0.1:{port}/db"]),
        ("serve, json, password file",
         ["serve", "--bind", "127.0.0.1:0", "--log-format", "json", "--database", f"postgres://u@127.0.0.1:{port}/db",
          "--database-password-file", password_file]),
        ("calibrate, password in the URL", ["calibrate", "--database", f"postgres://u:{password}@127.0.0.1:{port}/db"]),
    ]
    ok, results = True, []
    for name, argv in cases:
        started = time.monotonic()
        done = subprocess.run([args.bin, *argv], capture_output=True, text=True, env=serve_env(), cwd=ROOT, timeout=60,
                              stdin=subprocess.DEVNULL)
        output = done.stdout + done.stderr
        leaked = password in output
        redacted = "u:***@" in output
        ok &= done.returncode != 0 and not leaked
        results.append(f"{name}: exit {done.returncode} after {time.monotonic() - started:.2f} s, "
                       f"{'PASSWORD PRINTED' if leaked else 'no password'}{', the URL redacted' if redacted else ''}")
    return ok, "; ".join(results)


def challenge_flood(args, work, seconds=10.0, connections=8):
    """`POST /liveness/challenge` from 8 keep-alive connections of 127.0.0.1 for 10 s: the rows in
    the database stay within the cap (2,000), and 127.0.0.2 still gets its challenge."""
    server = Server(args.bin, work)
    counts = {}
    lock = threading.Lock()
    deadline = time.monotonic() + seconds

    def flood():
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
        while time.monotonic() < deadline:
            try:
                conn.request("POST", "/liveness/challenge")
                response = conn.getresponse()
                response.read()
                key = f"{response.status}" + (" with Retry-After" if response.getheader("Retry-After") else "")
            except OSError as e:
                key = type(e).__name__
                conn.close()
                conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
            with lock:
                counts[key] = counts.get(key, 0) + 1
        conn.close()

    try:
        threads = [threading.Thread(target=flood) for _ in range(connections)]
        for t in threads:
            t.start()
        time.sleep(seconds / 2)
        other = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30, source_address=("127.0.0.2", 0))
        other.request("POST", "/liveness/challenge")
        other_status = other.getresponse().status
        other.close()
        for t in threads:
            t.join()
        import sqlite3
        with sqlite3.connect(server.database) as db:
            rows = db.execute("SELECT count(*) FROM liveness_challenges").fetchone()[0]
    finally:
        server.stop()
    answered = ", ".join(f"{n:,} × {k}" for k, n in sorted(counts.items()))
    ok = rows <= 2000 and other_status == 201 and set(counts) <= {"201", "429 with Retry-After"}
    return ok, (f"{sum(counts.values()):,} requests from 127.0.0.1 in {seconds:.0f} s at {connections} connections: {answered}; "
                f"{rows:,} challenge rows in the database (target ≤ 2,000); 127.0.0.2 meanwhile got {other_status}")


def db_vanish(args, work):
    """The SQLite file deleted under the running server: /health 503 within 2 s, and no enrolment
    acknowledged after; the restart on the path says loudly that it made a new database."""
    server = Server(args.bin, work)
    acknowledged_after = refused = 0
    try:
        body, ctype = multipart([("subject", None, b"before"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, f"the enrolment before: {status}"
        os.remove(server.database)
        removed = time.monotonic()
        health_503 = None
        while time.monotonic() - removed < 5:
            status, data = server.request("GET", "/health")
            if status == 503 and problem_slug(data) == "store-unavailable":
                health_503 = time.monotonic() - removed
                break
            time.sleep(0.05)
        for n in range(10):
            body, ctype = multipart([("subject", None, f"after-{n}".encode()), ("image", "p.jpg", photo("01-1m.jpg"))])
            status, data = server.request("POST", "/enroll", body, {"Content-Type": ctype})
            acknowledged_after += status == 201
            refused += status == 503 and problem_slug(data) == "store-unavailable"
    finally:
        server.stop()
    restarted = Server(args.bin, work, database=server.database)
    try:
        with open(restarted.log_path) as f:
            warned = "NO DATABASE at" in f.read()
    finally:
        restarted.stop()
    ok = health_503 is not None and health_503 <= 2.0 and acknowledged_after == 0 and warned
    noticed = f"{health_503:.2f} s" if health_503 is not None else "NOT within 5 s"
    return ok, (f"database file deleted after one enrolment: /health 503 store-unavailable after {noticed} (target 2 s); "
                f"10 enrolments after: {acknowledged_after} acknowledged, {refused} refused 503 store-unavailable; the restart "
                f"{'warned' if warned else 'did NOT warn'} that it created a new, empty database")


SCENARIOS = {
    "slowloris": slowloris, "slow-body": slow_body, "kill9": kill9, "sigterm": sigterm, "stalled-heads": stalled_heads,
    "json-flood": json_flood, "trickle": trickle, "part-flood": part_flood, "duplicates": duplicates, "fail-closed": fail_closed,
    "db-down": db_down, "overload": overload, "secrets": secrets_scenario, "challenge-flood": challenge_flood,
    "db-vanish": db_vanish, "head-flood": head_flood, "slow-bodies": slow_bodies,
}
DEFAULT = ["slowloris", "slow-body", "kill9", "sigterm", "stalled-heads", "json-flood", "trickle", "part-flood", "duplicates",
           "fail-closed", "db-down", "secrets", "challenge-flood", "db-vanish", "head-flood", "slow-bodies"]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenarios", nargs="*", default=DEFAULT, help=", ".join(SCENARIOS))
    parser.add_argument("--bin", default=os.path.join(ROOT, "target", "debug", "facegate"))
    parser.add_argument("--storm-secs", type=float, default=4.0)
    parser.add_argument("--peak-secs", type=int, default=20)
    parser.add_argument("--overload-secs", type=int, default=60)
    parser.add_argument("--serve-flag", action="append", default=[], help="a flag for the overload scenario's server (repeat)")
    args = parser.parse_args()
    unknown = [s for s in args.scenarios if s not in SCENARIOS]
    if unknown:
        parser.error(f"unknown scenario(s) {unknown}: choose from {', '.join(SCENARIOS)}")
    failed = skipped = 0
    with tempfile.TemporaryDirectory() as work:
        for name in args.scenarios:
            try:
                ok, line = SCENARIOS[name](args, work)
            except Exception as e:  # a crash of the scenario counts as a failure
                ok, line = False, f"crashed: {e!r}"
            # ok is None: skipped, with the reason (counted as passed).
            print(f"{'SKIP' if ok is None else 'PASS' if ok else 'FAIL'} {name}: {line}", flush=True)
            failed += ok is False
            skipped += ok is None
    print(f"reliability: {len(args.scenarios) - failed - skipped} passed, {skipped} skipped, {failed} failed")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
