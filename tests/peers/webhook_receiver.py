#!/usr/bin/env python3
"""A webhook receiver that checks signatures with Python's own hmac module: the receiver of
coapcam's signed-webhook test (crates/coapcam/tests/it/webhook.rs).

Usage: webhook_receiver.py SECRET_FILE [CERT_FILE KEY_FILE]

Listens on a free port of 127.0.0.1 and prints "ready PORT". For each POST it checks the
header X-Coapcam-Signature: t=UNIX,v1=HEX against HMAC-SHA256 of b"UNIX." + body under
the file's secret (its bytes without a final line break) and a time within 300 s of its
own clock; it answers 204 when both hold and 401 otherwise, and prints one JSON line per
request: {"valid": true|false, "signature": HEADER, "body": BODY as text}. It runs until
it is killed. With CERT_FILE and KEY_FILE (PEM) it serves HTTPS with that certificate,
and a client that gives up the TLS handshake (it does not trust the certificate) is a
line {"tls_refused": REASON}. With WEBHOOK_RECEIVER_CLOSE=1 in its environment it closes
each connection after its answer (HTTP/1.0), so that every request comes on a new one.
"""

import hashlib
import hmac
import http.server
import json
import os
import ssl
import sys
import time

TOLERANCE_S = 300


def verify(secret, header, body):
    fields = dict(part.split("=", 1) for part in header.split(",") if "=" in part)
    try:
        unix = int(fields["t"])
    except (KeyError, ValueError):
        return False
    want = hmac.new(secret, f"{unix}.".encode() + body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(want, fields.get("v1", "")) and abs(time.time() - unix) <= TOLERANCE_S


def main():
    with open(sys.argv[1], "rb") as f:
        secret = f.read().rstrip(b"\r\n")

    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.0" if os.environ.get("WEBHOOK_RECEIVER_CLOSE") == "1" else "HTTP/1.1"

        def do_POST(self):
            body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
            header = self.headers.get("X-Coapcam-Signature", "")
            valid = verify(secret, header, body)
            self.send_response(204 if valid else 401)
            self.send_header("Content-Length", "0")
            self.end_headers()
            line = {"valid": valid, "signature": header, "body": body.decode("utf-8", "replace")}
            print(json.dumps(line), flush=True)

        def log_message(self, *args):
            pass

    class Server(http.server.ThreadingHTTPServer):
        tls = None

        def get_request(self):
            sock, addr = self.socket.accept()
            if self.tls is None:
                return sock, addr
            try:
                return self.tls.wrap_socket(sock, server_side=True), addr
            except ssl.SSLError as e:
                print(json.dumps({"tls_refused": e.reason}), flush=True)
                sock.close()
                raise

    server = Server(("127.0.0.1", 0), Handler)
    if len(sys.argv) == 4:
        server.tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        server.tls.load_cert_chain(sys.argv[2], sys.argv[3])
    print(f"ready {server.server_address[1]}", flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
