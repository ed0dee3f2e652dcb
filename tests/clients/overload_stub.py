"""A stand-in for an overloaded facegate, for the examples' retry path: every other request (the
first, third, ...) is answered `overloaded` (503, Retry-After: 1) and the others are forwarded to
the real server. python overload_stub.py UPSTREAM_URL; prints its own URL on the first line."""

import sys
import urllib.error
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

upstream = sys.argv[1]
OVERLOADED = (
    b'{"type":"https://facegate.dev/problems/overloaded","title":"Overloaded","status":503,'
    b'"detail":"the work queue is full; retry after the Retry-After delay"}'
)


class Stub(BaseHTTPRequestHandler):
    requests = 0

    def do_POST(self):
        body = self.rfile.read(int(self.headers.get("content-length", 0)))
        Stub.requests += 1
        if Stub.requests % 2 == 1:
            self.answer(503, "application/problem+json", OVERLOADED, {"Retry-After": "1"})
            return
        forwarded = urllib.request.Request(upstream + self.path, data=body, method="POST")
        forwarded.add_header("Content-Type", self.headers["content-type"])
        try:
            with urllib.request.urlopen(forwarded, timeout=60) as r:
                self.answer(r.status, r.headers["content-type"], r.read())
        except urllib.error.HTTPError as e:
            self.answer(e.code, e.headers["content-type"], e.read())

    def answer(self, status, content_type, body, headers=None):
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


server = ThreadingHTTPServer(("127.0.0.1", 0), Stub)
print(f"http://127.0.0.1:{server.server_address[1]}", flush=True)
server.serve_forever()
