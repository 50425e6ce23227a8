"""The viewer's file server serves only regular, single-link, non-hidden files inside its bundle, only to
requests whose ``Host`` names the bound loopback address, and answers one identical 404 for everything it
refuses (loopback only; no browser needed)."""

import os
import socket

import pytest

from bench.hostile import http_exchange, stalled_then_get
from omnirecon.viewer.server import MAX_CONNECTIONS, BundleRequestHandler, ViewerServer, host_allowed


def raw_get(port: int, target: str, host: str | None = "127.0.0.1") -> tuple[int, bytes]:
    """Send ``GET target`` exactly as given with the given ``Host`` header (None: no header)."""
    head = f"GET {target} HTTP/1.0\r\n" + (f"Host: {host}\r\n" if host is not None else "") + "\r\n"
    return http_exchange(port, head.encode())


@pytest.fixture
def served(tmp_path):
    root = tmp_path / "bundle"
    (root / "sub").mkdir(parents=True)
    (root / "index.html").write_text("<p>viewer</p>")
    (root / "sub" / "data.bin").write_bytes(b"\x00\x01")
    outside = tmp_path / "outside.txt"
    outside.write_text("TOP SECRET")
    os.link(outside, root / "hard.txt")  # a hard link: an inode that lives outside the bundle
    (root / ".env").write_text("TOP SECRET dotfile")
    (root / ".viewer.abc").mkdir()
    (root / ".viewer.abc" / "index.html").write_text("TOP SECRET half-written")
    os.symlink(".env", root / "to_dotfile.txt")
    os.symlink("/etc", root / "etc")  # exists outside
    os.symlink("/no/such/folder", root / "nowhere")  # does not exist outside
    os.mkfifo(root / "fifo")
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    try:
        yield server.server_address[1]
    finally:
        server.stop()


def test_serves_plain_files(served):
    port = served
    assert raw_get(port, "/index.html") == (200, b"<p>viewer</p>")
    assert raw_get(port, "/sub/data.bin", host=f"127.0.0.1:{port}") == (200, b"\x00\x01")
    assert raw_get(port, "/", host=f"localhost:{port}") == (200, b"<p>viewer</p>")


def test_refuses_hard_links(served):
    status, body = raw_get(served, "/hard.txt")
    assert status == 404 and b"TOP SECRET" not in body


@pytest.mark.parametrize("target", ["/.env", "/.viewer.abc/index.html", "/to_dotfile.txt", "/%2eenv"])
def test_refuses_dotfiles_and_dot_folders(served, target):
    status, body = raw_get(served, target)
    assert status == 404 and b"TOP SECRET" not in body, target


def test_refuses_non_regular_files(served):
    assert raw_get(served, "/fifo")[0] == 404
    assert raw_get(served, "/sub")[0] == 404


@pytest.mark.parametrize("host", ["evil.example:{port}", "evil.example", "127.0.0.1:1", "localhost.evil:{port}",
                                  "", None, "127.0.0.2:{port}"])
def test_refuses_foreign_host_headers(served, host):
    host = None if host is None else host.format(port=served)
    assert raw_get(served, "/index.html", host=host)[0] == 404, host


def test_one_identical_404_for_refused_and_missing(served):
    """A symbolic link to an existing outside folder and one to a missing folder, a missing file and a
    traversal all get byte-identical answers, so nothing reveals what exists outside the bundle."""
    answers = {t: raw_get(served, t) for t in ["/etc/passwd", "/etc/hostname", "/nowhere/x", "/missing.txt",
                                               "/../outside.txt", "/hard.txt", "/.env"]}
    assert {status for status, _ in answers.values()} == {404}
    assert len({body for _, body in answers.values()}) == 1, answers


def test_host_allowed():
    assert host_allowed("127.0.0.1:8765", 8765) and host_allowed("LOCALHOST:8765", 8765)
    assert host_allowed("127.0.0.1", 8765) and host_allowed("localhost", 8765)
    assert not host_allowed("127.0.0.1:8766", 8765) and not host_allowed("attacker.test:8765", 8765)
    assert not host_allowed(None, 8765) and not host_allowed("", 8765)


@pytest.mark.parametrize("hosts", [("127.0.0.1", "evil.example"), ("evil.example", "127.0.0.1"),
                                   ("127.0.0.1", "127.0.0.1")])
def test_two_host_headers_are_a_bad_request(served, hosts):
    """Which of two Host headers a proxy honours differs: good-then-evil must not be served (400)."""
    head = "GET /index.html HTTP/1.1\r\n" + "".join(f"Host: {h}\r\n" for h in hosts) + "Connection: close\r\n\r\n"
    assert http_exchange(served, head.encode())[0] == 400


def test_client_disconnect_mid_response_is_quiet(tmp_path, capfd):
    """A client that closes the socket while a large file is sent leaves no traceback on stderr."""
    import struct
    import time

    root = tmp_path / "bundle"
    root.mkdir()
    (root / "index.html").write_text("<p>viewer</p>")
    (root / "big.bin").write_bytes(os.urandom(32 * 1024 * 1024))
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    try:
        port = server.server_address[1]
        for _ in range(3):
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close with a reset
            s.sendall(b"GET /big.bin HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
            s.recv(1024)
            s.close()
        time.sleep(1.0)
        assert raw_get(port, "/index.html") == (200, b"<p>viewer</p>")  # still serving
    finally:
        server.stop()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Error" not in err, err


def test_stalled_connections_hold_no_thread_and_never_starve_a_request(tmp_path):
    """1,000 connections that send a request line and never finish their headers: no thread is started for them (one
    reader thread holds them all), and a normal GET from another client is answered."""
    import resource
    import threading
    import time

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if min(hard, 4096) < 2300:
        pytest.skip("needs 2,300 file descriptors (both ends of 1,000 connections in this process)")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 4096)), hard))
    root = tmp_path / "bundle"
    root.mkdir()
    (root / "index.html").write_text("<p>viewer</p>")
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    threads = threading.active_count()
    port = server.server_address[1]
    held = []
    try:
        for _ in range(1000):
            held.append(socket.create_connection(("127.0.0.1", port), timeout=5))
            held[-1].sendall(b"GET /index.html HTTP/1.1\r\n")
        time.sleep(0.5)
        assert threading.active_count() == threads and len(server.reader.waiting) == 1000
        assert raw_get(port, "/index.html") == (200, b"<p>viewer</p>")
        assert stalled_then_get(port, 100, timeout=5.0)[0] == 200
    finally:
        for s in held:
            s.close()
        server.stop()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_clients_that_never_read_a_large_file_give_way_to_a_new_request(tmp_path):
    """MAX_CONNECTIONS + 16 clients request a 16 MB file and never read it (every serving slot held): a normal GET
    takes the place of one that has read nothing for STUCK seconds and is answered, not refused with 503."""
    import time

    from omnirecon.viewer.server import STUCK

    root = tmp_path / "bundle"
    root.mkdir()
    (root / "index.html").write_text("<p>viewer</p>")
    (root / "big.bin").write_bytes(os.urandom(16 * 2**20))
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    port = server.server_address[1]
    held = []
    try:
        for _ in range(MAX_CONNECTIONS + 16):
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(b"GET /big.bin HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
            held.append(s)
        time.sleep(STUCK + 0.3)
        assert raw_get(port, "/index.html") == (200, b"<p>viewer</p>")
    finally:
        for s in held:
            s.close()
        server.stop()


def test_a_stalled_connection_is_closed_after_the_idle_timeout(tmp_path, monkeypatch):
    assert 0 < BundleRequestHandler.timeout <= 60  # the shipped timeout (seconds), shortened below
    monkeypatch.setattr(BundleRequestHandler, "timeout", 0.5)
    root = tmp_path / "bundle"
    root.mkdir()
    (root / "index.html").write_text("<p>viewer</p>")
    server = ViewerServer(root, port=0, quiet=True)
    server.start()
    try:
        with socket.create_connection(("127.0.0.1", server.server_address[1]), timeout=5) as s:
            s.sendall(b"GET /index.html HTTP/1.1\r\n")
            assert s.recv(1024) == b""  # the server closed it (a hang would raise TimeoutError after 5 s)
    finally:
        server.stop()


def test_a_browser_that_never_answers_is_started_again(tmp_path):
    """A browser that does not answer its first protocol command in time is ended and a new one started
    (at most ``HeadlessChromium.STARTS``). The browser is a stand-in that speaks the DevTools pipe protocol (fd 3
    in, fd 4 out, NUL-terminated JSON), so the test does not wait on a real Chromium's start under load."""
    import stat
    import sys

    from omnirecon.viewer.headless import BrowserTimeout, HeadlessChromium

    starts = tmp_path / "starts"
    script = tmp_path / "browser"
    # start 1 holds the pipe open and never answers; later starts answer every command
    script.write_text(f"""#!{sys.executable}
import json, os, time
with open({str(starts)!r}, "a") as f:
    f.write("x\\n")
if len(open({str(starts)!r}).read().split()) <= 1:
    time.sleep(60)
RESULTS = {{"Target.getTargets": {{"targetInfos": [{{"type": "page", "targetId": "t1"}}]}},
           "Target.attachToTarget": {{"sessionId": "s1"}},
           "Runtime.evaluate": {{"result": {{"type": "number", "value": 2}}}}}}
buf = b""
while True:
    chunk = os.read(3, 65536)
    if not chunk:
        break
    buf += chunk
    while b"\\0" in buf:
        raw, buf = buf.split(b"\\0", 1)
        msg = json.loads(raw)
        os.write(4, json.dumps({{"id": msg["id"], "result": RESULTS.get(msg["method"], {{}})}}).encode() + b"\\0")
        if msg["method"] == "Browser.close":
            raise SystemExit(0)
""")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    with HeadlessChromium(64, 48, executable=str(script), timeout=3) as browser:
        assert browser.evaluate("1 + 1") == 2
    assert len(starts.read_text().split()) == 2
    starts.write_text("")  # every start silent now: after STARTS starts the timeout is raised
    script.write_text(script.read_text().replace("<= 1", "<= 99"))
    with pytest.raises(BrowserTimeout):
        HeadlessChromium(64, 48, executable=str(script), timeout=1)
    assert len(starts.read_text().split()) == HeadlessChromium.STARTS
