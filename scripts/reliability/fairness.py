"""Fair shares under floods from other addresses (the scenarios `head-flood` and `slow-bodies` of
reliability.py, which imports this file).

Both measure 4 legitimate clients on 127.0.0.1 verifying IMM 01-2m against the enrolled 01-1m, one
new connection per request, first for 8 s unattacked, then for 12 s under the flood; the target
is >= 95 % of their verifications answered 200 and >= 50 % of their unattacked throughput.

  head-flood   4,000 complete `POST /verify` heads without a body from 127.0.0.2, each opened
               again once answered (at most 1,000 a second), and 8 bodies of 16 MiB - 1 byte from 127.0.0.3 sent at once
               but their last byte, then stalled (opened again once answered); also: the server's
               peak RSS growth (VmHWM, reset when the flood starts, - VmRSS before) <= 200 MB
  slow-bodies  64 addresses (127.0.1.1-64) x 16 bodies declaring 16 MiB - 1 byte sent at 8.5 KiB/s
               (just above the minimum rate), each opened again once answered
"""

import resource
import selectors
import socket
import threading
import time

LEGIT_CLIENTS = 4
BASELINE_S = 8.0
ATTACK_S = 12.0
BIG = 16 * 1024 * 1024 - 1
# The heads answered are opened again at most this often: about 0.8 Mbit/s of heads, four times
# the flood the issue measured (0.2 Mbit/s). Unbounded, the script itself takes a whole core of a
# 2-core machine reconnecting, which measures the script, not the server.
REOPEN_PER_S = 1000


def raise_fd_limit():
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def head(length):
    return (f"POST /verify HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
            f"Content-Length: {length}\r\n\r\n").encode()


class Flood:
    """`count` connections from each of `sources`, each sending `head`, then `rate` bytes a second
    (0: nothing more), opened again once answered, at most `reopen_per_s` a second (None: at once);
    one thread, non-blocking sockets."""

    def __init__(self, port, sources, count, first, rate=0, reopen_per_s=None):
        self.port, self.sources, self.count, self.first, self.rate = port, sources, count, first, rate
        self.reopen_per_s = reopen_per_s
        self.to_reopen = []
        self.selector = selectors.DefaultSelector()
        self.answers = {}
        self.opened = 0
        self.done = False
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _open(self, source):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setblocking(False)
        try:
            s.bind((source, 0))
            s.connect_ex(("127.0.0.1", self.port))
        except OSError:
            s.close()
            return False
        self.selector.register(s, selectors.EVENT_WRITE, {"source": source, "sent": False, "next": 0.0})
        self.opened += 1
        return True

    def _close(self, s, answer):
        self.answers[answer] = self.answers.get(answer, 0) + 1
        source = self.selector.get_key(s).data["source"]
        self.selector.unregister(s)
        s.close()
        if self.done:
            return
        if self.reopen_per_s is None:
            self._open(source)
        else:
            self.to_reopen.append(source)

    def _run(self):
        for source in self.sources:
            for _ in range(self.count):
                self._open(source)
        # The rate in four pieces a second, looked at every 50 ms: a smaller piece more often is
        # the same flood to the server, but costs this script a core of the machine it shares.
        piece = b"-" * max(1, int(self.rate / 4))
        next_scan = 0.0
        last = time.monotonic()
        allowance = 0.0
        while not self.done:
            now = time.monotonic()
            if self.reopen_per_s is not None:
                allowance = min(allowance + (now - last) * self.reopen_per_s, self.reopen_per_s)
                while self.to_reopen and allowance >= 1:
                    self._open(self.to_reopen.pop())
                    allowance -= 1
            last = now
            for key, events in self.selector.select(timeout=0.01):
                s, data = key.fileobj, key.data
                if events & selectors.EVENT_WRITE and not data["sent"]:
                    try:
                        s.send(self.first)
                        data["sent"], data["next"] = True, now + 0.25
                        self.selector.modify(s, selectors.EVENT_READ, data)
                    except BlockingIOError:
                        pass
                    except OSError:
                        self._close(s, "connect failed")
                    continue
                if events & selectors.EVENT_READ:
                    try:
                        got = s.recv(512)
                    except (BlockingIOError, InterruptedError):
                        continue
                    except OSError:
                        got = b""
                    line = got.split(b"\r\n", 1)[0].decode(errors="replace")[9:12] if got else "closed"
                    self._close(s, line or "closed")
            if self.rate and now >= next_scan:
                next_scan = now + 0.05
                for key in list(self.selector.get_map().values()):
                    data = key.data
                    if data["sent"] and now >= data["next"]:
                        # Without drift: a late piece does not lower the rate.
                        data["next"] += 0.25
                        try:
                            key.fileobj.send(piece)
                        except (BlockingIOError, InterruptedError):
                            pass
                        except OSError:
                            self._close(key.fileobj, "reset")
        for key in list(self.selector.get_map().values()):
            key.fileobj.close()

    def start(self):
        self.thread.start()

    def stop(self):
        self.done = True
        self.thread.join()


class StalledBodies:
    """`n` connections from `source`, each sending a head declaring BIG bytes and all of the body
    but its last byte at once, then nothing; opened again once answered."""

    def __init__(self, port, source, n):
        self.port, self.source, self.n = port, source, n
        self.answers = {}
        self.done = False
        self.lock = threading.Lock()
        self.threads = [threading.Thread(target=self._one, daemon=True) for _ in range(n)]

    def _one(self):
        body = head(BIG) + b"x" * (BIG - 1)
        while not self.done:
            try:
                s = socket.create_connection(("127.0.0.1", self.port), timeout=30, source_address=(self.source, 0))
                s.sendall(body)
                s.settimeout(0.5)
                got = b""
                while not self.done and not got:
                    try:
                        got = s.recv(512) or b"closed"
                    except socket.timeout:
                        continue
                answer = got.split(b"\r\n", 1)[0].decode(errors="replace")[9:12] if got.startswith(b"HTTP") else "closed"
            except OSError as e:
                answer = type(e).__name__
                time.sleep(0.1)
            finally:
                try:
                    s.close()
                except Exception:
                    pass
            with self.lock:
                self.answers[answer] = self.answers.get(answer, 0) + 1

    def start(self):
        for t in self.threads:
            t.start()

    def stop(self):
        self.done = True
        for t in self.threads:
            t.join(timeout=35)


def legit_run(server, probe, ctype, seconds):
    """4 clients verifying for `seconds`, each request on a new connection: (answers, 200s/s)."""
    tally, lock = {}, threading.Lock()
    stop = time.monotonic() + seconds

    def client():
        while time.monotonic() < stop:
            try:
                status, _ = server.request("POST", "/verify", probe, {"Content-Type": ctype}, timeout=30)
            except OSError as e:
                status = type(e).__name__
            with lock:
                tally[status] = tally.get(status, 0) + 1
            if status == 503:
                time.sleep(1.0)

    threads = [threading.Thread(target=client) for _ in range(LEGIT_CLIENTS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return tally, tally.get(200, 0) / seconds


def fair_share(args, work, server_class, multipart, photo, verify_multipart, attack):
    raise_fd_limit()
    server = server_class(args.bin, work)
    try:
        body, ctype = multipart([("subject", None, b"imm01"), ("image", "p.jpg", photo("01-1m.jpg"))])
        status, _ = server.request("POST", "/enroll", body, {"Content-Type": ctype})
        assert status == 201, f"enrolling IMM 01-1m: {status}"
        probe, ctype = verify_multipart("imm01", "01-2m.jpg")
        _, unattacked = legit_run(server, probe, ctype, BASELINE_S)
        rss_before = server.rss_mb()
        server.reset_peak_rss()
        floods = attack(server.port)
        for f in floods:
            f.start()
        time.sleep(2.0)  # the flood has taken what it can
        tally, attacked = legit_run(server, probe, ctype, ATTACK_S)
        growth = server.peak_rss_mb() - rss_before
        for f in floods:
            f.stop()
        health, _ = server.request("GET", "/health")
    finally:
        server.stop()
    answered = sum(tally.values())
    ok_share = tally.get(200, 0) / max(answered, 1)
    ratio = attacked / unattacked if unattacked else 0.0
    return tally, ok_share, ratio, attacked, unattacked, growth, health, [f.answers for f in floods]


def head_flood(args, work, server_class, multipart, photo, verify_multipart):
    def attack(port):
        return [Flood(port, ["127.0.0.2"], 4000, head(100_000), reopen_per_s=REOPEN_PER_S), StalledBodies(port, "127.0.0.3", 8)]

    tally, ok_share, ratio, attacked, unattacked, growth, health, answers = fair_share(
        args, work, server_class, multipart, photo, verify_multipart, attack)
    ok = ok_share >= 0.95 and ratio >= 0.5 and growth <= 200 and health == 200
    return ok, (f"4,000 heads without a body from 127.0.0.2 (reopened at most {REOPEN_PER_S}/s) and 8 bodies of 16 MiB - 1 byte sent at once then stalled from "
                f"127.0.0.3, for {ATTACK_S:.0f} s: legitimate verifications {tally} ({100 * ok_share:.1f} % 200), "
                f"{attacked:.2f}/s against {unattacked:.2f}/s unattacked ({100 * ratio:.0f} %); VmHWM growth {growth:.0f} MB; "
                f"heads answered {answers[0]}; stalled bodies answered {answers[1]}; /health then {health}")


def slow_bodies(args, work, server_class, multipart, photo, verify_multipart):
    sources = [f"127.0.1.{i}" for i in range(1, 65)]

    def attack(port):
        return [Flood(port, sources, 16, head(BIG), rate=8.5 * 1024)]

    tally, ok_share, ratio, attacked, unattacked, growth, health, answers = fair_share(
        args, work, server_class, multipart, photo, verify_multipart, attack)
    ok = ratio >= 0.5 and health == 200
    return ok, (f"64 addresses x 16 bodies of 16 MiB - 1 byte at 8.5 KiB/s for {ATTACK_S:.0f} s: legitimate verifications "
                f"{tally} ({100 * ok_share:.1f} % 200), {attacked:.2f}/s against {unattacked:.2f}/s unattacked "
                f"({100 * ratio:.0f} %); VmHWM growth {growth:.0f} MB; bodies answered {answers[0]}; /health then {health}")
