"""``viewer``: HTTP requests with several ``Host`` headers (must be 400), clients that disconnect, and up to 1,000
connections that stall in their headers while a normal request must be answered within 1 s; bad requests (huge or
endless headers, garbage, HTTP/0.9, traversal in every spelling, CONNECT, a body never sent), a slowloris trickle,
clients that request a large file and never read it, connections that send nothing. Each case starts a
``ViewerServer`` on a temporary folder in the forked child (:func:`http_case`)."""

from __future__ import annotations

import os
import resource
import shutil
import socket
import struct
import sys
import tempfile
import time
from pathlib import Path


def viewer_cases() -> list[dict]:
    """Several ``Host`` headers, disconnecting clients, stalled connections."""
    out = []
    for hosts in [("127.0.0.1", "evil.example"), ("evil.example", "127.0.0.1"), ("127.0.0.1", "127.0.0.1"),
                  ("localhost", "127.0.0.1"), ("127.0.0.1", ""), ("127.0.0.1", "evil.example", "127.0.0.1")]:
        out.append({"class": "viewer", "args": ["http_hosts", *hosts], "named": None})
    for n in (1, 2, 5):
        out.append({"class": "viewer", "args": ["http_disconnect", str(n)], "named": None})
    for n in (100, 1000):
        out.append({"class": "viewer", "args": ["http_stalled", str(n)], "named": None})
    return out


def request_cases() -> list[dict]:
    """Each of BAD_REQUESTS, a slowloris trickle, slow readers of a large file, silent connections."""
    out = [{"class": "viewer", "args": ["http_raw", name], "named": None} for name in BAD_REQUESTS]
    out += [{"class": "viewer", "args": [kind, str(n)], "named": None}
            for kind, n in (("http_trickle", 50), ("http_slow_readers", 100), ("http_silent", 1000))]
    return out


def http_exchange(port: int, request: bytes) -> tuple[int, bytes]:
    """Send ``request`` to 127.0.0.1:``port`` exactly as given; the status code and body of the answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(request)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def stalled_then_get(port: int, stalled: int, timeout: float = 1.0) -> tuple[int, float]:
    """Open ``stalled`` connections to 127.0.0.1:``port`` that send a request line and never finish their
    headers, then send one normal ``GET /index.html``: its status (0 when no answer came within ``timeout``
    seconds) and the seconds it took. The stalled sockets are closed before returning."""
    if stalled + 64 > resource.getrlimit(resource.RLIMIT_NOFILE)[0]:
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, stalled + 256), hard))
    held = []
    try:
        for _ in range(stalled):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.sendall(b"GET /index.html HTTP/1.1\r\n")
            held.append(s)
        t0 = time.perf_counter()
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
                s.sendall(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
                head = s.recv(64)
            status = int(head.split()[1]) if head.startswith(b"HTTP/") else 0
        except OSError:
            status = 0
        return status, time.perf_counter() - t0
    finally:
        for s in held:
            s.close()


H = "Host: 127.0.0.1\r\n"
BAD_REQUESTS = {
    "big_header": f"GET /index.html HTTP/1.0\r\n{H}X-Big: {'a' * 70_000}\r\n\r\n",
    "many_headers": "GET /index.html HTTP/1.0\r\n" + H + "".join(f"X-{i}: v\r\n" for i in range(300)) + "\r\n",
    "long_line": f"GET /{'a' * 70_000} HTTP/1.0\r\n{H}\r\n", "garbage": "\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n",
    "http09": "GET /index.html\r\n\r\n", "post_huge": f"POST /index.html HTTP/1.0\r\n{H}Content-Length: 10000000000\r\n\r\n",
    "bad_version": f"GET /index.html HTTP/9.9\r\n{H}\r\n", "no_colon": "GET /index.html HTTP/1.0\r\nHost 127.0.0.1\r\n\r\n",
    "nul_path": f"GET /index.html%00.png HTTP/1.0\r\n{H}\r\n", "dotdot": f"GET /../../../../etc/passwd HTTP/1.0\r\n{H}\r\n",
    "dotdot_encoded": f"GET /%2e%2e/%2e%2e/%2e%2e/etc/passwd HTTP/1.0\r\n{H}\r\n",
    "slash_encoded": f"GET /..%2f..%2f..%2fetc%2fpasswd HTTP/1.0\r\n{H}\r\n", "double_slash": f"GET //etc/passwd HTTP/1.0\r\n{H}\r\n",
    "absolute": f"GET http://127.0.0.1/../etc/passwd HTTP/1.0\r\n{H}\r\n", "bad_utf8": f"GET /%ff%fe HTTP/1.0\r\n{H}\r\n",
    "connect": f"CONNECT 127.0.0.1:22 HTTP/1.1\r\n{H}\r\n", "trace": f"TRACE / HTTP/1.1\r\n{H}\r\n",
    "long_host": f"GET /index.html HTTP/1.0\r\nHost: {'a' * 60_000}\r\n\r\n", "bare_lf": "GET /index.html HTTP/1.0\nHost: 127.0.0.1\n\n",
    "pipelined": f"GET /index.html HTTP/1.1\r\n{H}\r\nGET /big.bin HTTP/1.1\r\n{H}\r\n",
    "range_bad": f"GET /big.bin HTTP/1.1\r\n{H}Range: bytes=999999999-1\r\nConnection: close\r\n\r\n",
}
"""Requests a hostile client sends the viewer: each gets an answer that serves nothing outside the folder (or the
connection is closed), and the server then answers a normal GET within 1 s."""


def _raw_answer(port: int, raw: bytes) -> bytes:
    """What the server sends back to ``raw`` (the client half-closes after sending; b"" when it closes first)."""
    data = b""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        try:
            s.sendall(raw)
            s.shutdown(socket.SHUT_WR)
            while chunk := s.recv(65536):
                data += chunk
        except OSError:  # reset by the server (a request it refused while still sending)
            pass
    return data


def _clients(port: int, kind: str, n: int) -> list:
    """``n`` hostile connections: ``http_trickle`` sends a request a byte at a time (slowloris), ``http_slow_readers``
    requests the 16 MB file and never reads, ``http_silent`` connects and sends nothing."""
    held = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=10)
        if kind == "http_slow_readers":
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(f"GET /big.bin HTTP/1.0\r\n{H}\r\n".encode())
        elif kind == "http_trickle":
            s.sendall(b"G")
        held.append(s)
    if kind == "http_trickle":
        for byte in b"ET /index.html HTTP/1.0\r\nX-":
            time.sleep(0.05)
            for s in held:
                s.sendall(bytes([byte]))
    time.sleep(0.3)
    return held


def http_case(argv: list[str]) -> int:
    """0 when the viewer answers as it must: 400 for several Host headers; quiet and alive after disconnects."""
    from omnirecon.viewer.server import ViewerServer

    folder = Path(tempfile.mkdtemp(prefix="hostile_view_"))
    (folder / "index.html").write_text("<p>ok</p>")
    (folder / "big.bin").write_bytes(os.urandom(16 * 2**20))
    server = ViewerServer(folder, port=0, quiet=True)
    server.start()
    port = server.server_address[1]

    def get(raw: bytes) -> int:
        return http_exchange(port, raw)[0]
    try:
        if argv[0] == "http_stalled":  # the stalled connections must not keep a normal request waiting
            status, seconds = stalled_then_get(port, int(argv[1]), timeout=1.0)
            print(f"GET answered {status} in {seconds:.3f} s beside {argv[1]} stalled connections", file=sys.stderr)
            return 0 if status == 200 and seconds <= 1.0 else 3
        if argv[0] == "http_raw":  # a bad request: no file outside the folder, and the server goes on
            answer = _raw_answer(port, BAD_REQUESTS[argv[1]].encode("latin-1"))
            status = answer.split(b" ", 2)[1].decode() if answer.startswith(b"HTTP/") else "closed"
            print(f"answered {status}", file=sys.stderr)
            leaked = b"root:" in answer or (status == "200" and argv[1] not in ("bare_lf", "pipelined", "range_bad"))
            return 3 if leaked or get(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n") != 200 else 0
        if argv[0] in ("http_trickle", "http_slow_readers", "http_silent"):
            held = _clients(port, argv[0], int(argv[1]))
            try:
                status, seconds = stalled_then_get(port, 0, timeout=1.0)
            finally:
                for s in held:
                    s.close()
            print(f"GET answered {status} in {seconds:.3f} s beside {argv[1]} {argv[0][5:]} connections", file=sys.stderr)
            return 0 if status == 200 and seconds <= 1.0 else 3
        if argv[0] == "http_hosts":
            head = "GET /index.html HTTP/1.1\r\n" + "".join(f"Host: {h}\r\n" for h in argv[1:]) + "Connection: close\r\n\r\n"
            return 0 if get(head.encode()) == 400 else 3
        for _ in range(int(argv[1])):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.sendall(b"GET /big.bin HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
            s.recv(1024)
            s.close()
        time.sleep(0.5)
        return 0 if get(b"GET /index.html HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n") == 200 else 3
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)

