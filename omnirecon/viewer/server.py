"""A static file server for viewer bundles, bound to 127.0.0.1, that never serves outside its folder.

:class:`BundleRequestHandler` (an ``http.server.SimpleHTTPRequestHandler``) answers ``GET`` / ``HEAD``
only, for regular files under its root. It answers one identical 404 (no 403 that would reveal what
exists) to any request whose ``Host`` header is not the bound address (``127.0.0.1:PORT`` or
``localhost:PORT``, the port optional: a DNS-rebinding page sends its own host name; a request with
two ``Host`` headers gets 400), whose path is not
a plain ``/``-rooted path (absolute-form ``http://...`` targets, backslashes, NUL bytes), has a ``..``
or ``.`` segment (also percent-encoded) or a dotfile / dot-folder segment, resolves (symbolic links
followed) to anything outside the root or to a hidden name, is not a regular file, or has more than
one hard link (a hard link can name an inode outside the bundle); it does not list folders.
Responses are not cached, so a re-exported bundle shows at once. A client that disconnects mid-response
is not reported (no traceback on the terminal).

Clients that connect and stall cannot starve the others. No thread waits on a request's headers: one reader
thread (:class:`HeaderReader`, a ``selectors`` loop) collects every new connection's request line and headers,
closes a connection that has not sent them within :data:`IDLE_TIMEOUT` seconds of connecting (a trickle of bytes
does not extend it) or whose headers pass :data:`MAX_HEAD` bytes, and, when more connections wait on their headers
than the file-descriptor limit leaves room for (:func:`waiting_cap`), closes the oldest waiting one. A connection
whose headers are complete gets a thread of its own, whose socket reads and writes wait at most
:data:`IDLE_TIMEOUT` seconds each; at most :data:`MAX_CONNECTIONS` are served at once: beyond them a new one takes
the place of the served one whose client has read nothing for the longest, at least :data:`STUCK` seconds (a client
that requests a large file and never reads it), else it is answered 503. So a normal request is answered at once
however many stalled connections are open.

Size: the path checks, the header reader and the connection rules are one concern, serving a folder to hostile clients.
"""

from __future__ import annotations

import http.server
import io
import os
import posixpath
import re
import resource
import selectors
import socket
import stat
import threading
import time
import urllib.parse
from functools import partial
from pathlib import Path

from omnirecon.errors import InputError
from omnirecon.options import check_value
from omnirecon.viewer.format import check_bundle

HOST = "127.0.0.1"
DISCONNECTS = (ConnectionError, TimeoutError)
"""A client closing the connection mid-response (BrokenPipe, ConnectionReset, ConnectionAborted) or timing out."""
IDLE_TIMEOUT = 10.0
"""Seconds a connection's socket read or write may wait before the connection is closed."""
MAX_CONNECTIONS = 64
"""Connections served at once once their headers are in (a thread each); beyond it a new one takes a stuck one's place
(:data:`STUCK`) or is answered 503."""
STUCK = 0.2
"""Seconds a served client may go without reading before a new connection beyond :data:`MAX_CONNECTIONS` takes its place."""
COPY_CHUNK = 65536
"""Bytes of a file sent per write (the client's progress is noted between writes)."""
MAX_HEAD = 65536
"""Bytes of request line and headers a connection may send; beyond them it is closed."""
HEAD_END = re.compile(rb"\r?\n\r?\n")
TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".json": "application/json",
         ".glb": "model/gltf-binary", ".bin": "application/octet-stream", ".ply": "application/octet-stream",
         ".png": "image/png", ".html": "text/html; charset=utf-8", ".css": "text/css", "": "application/octet-stream"}


def host_allowed(host: str | None, port: int) -> bool:
    """Whether a ``Host`` header names the bound address: ``127.0.0.1`` or ``localhost``, with ``port``
    or without a port."""
    if not host:
        return False
    name, _, given = host.strip().lower().rpartition(":") if ":" in host else (host.strip().lower(), "", "")
    return name in (HOST, "localhost") and given in ("", str(port))


class BundleRequestHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the regular files under ``directory`` (keyword argument) and nothing else."""

    extensions_map = TYPES
    timeout = IDLE_TIMEOUT  # socket timeout for every read and write (StreamRequestHandler.setup)
    server_version = "omnirecon-view"
    sys_version = ""

    def __init__(self, *args, directory: str, quiet: bool = False, **kwargs):
        self.quiet = quiet
        super().__init__(*args, directory=str(Path(directory).resolve()), **kwargs)

    def resolve(self) -> tuple[int, Path | None]:
        """``(status, file)``: 200 and the file to send, 400 for a request with more than one ``Host`` header
        (which one a proxy or browser honours differs: never guess), or 404 for everything refused or missing."""
        if len(self.headers.get_all("Host") or []) > 1:
            return 400, None
        if not host_allowed(self.headers.get("Host"), self.server.server_address[1]):
            return 404, None  # DNS rebinding: a foreign page reaching 127.0.0.1 under its own name
        target = self.path
        if not target.startswith("/") or target.startswith("//"):
            return 404, None  # absolute-form (http://host/...) or network-path targets
        path = urllib.parse.urlsplit(target).path
        try:
            path = urllib.parse.unquote(path, errors="strict")
        except UnicodeDecodeError:
            return 404, None
        if "\\" in path or "\0" in path:
            return 404, None
        parts = path.split("/")[1:]
        if any(p.startswith(".") for p in parts):
            return 404, None  # ".", "..", dotfiles and dot-folders (e.g. a half-written .viewer.* folder)
        if path.endswith("/"):
            parts = [*parts[:-1], "index.html"]
        root = Path(self.directory)
        file = root.joinpath(*[p for p in parts if p])
        try:
            real = file.resolve(strict=True)
        except (FileNotFoundError, NotADirectoryError, OSError, RuntimeError):
            return 404, None
        if real != root and root not in real.parents:
            return 404, None  # e.g. a symbolic link out of the folder
        if any(p.startswith(".") for p in real.relative_to(root).parts):
            return 404, None  # a link inside the bundle to a hidden name
        try:
            st = os.stat(real)
        except OSError:
            return 404, None
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
            return 404, None  # folders, devices, FIFOs; hard links (the inode may live outside the bundle)
        return 200, real

    def setup(self) -> None:
        super().setup()
        self.rfile.close()
        self.rfile = io.BytesIO(self.server.take_head(self.request))  # read by the HeaderReader (HTTP/1.0: one request)
        # a send buffer of a few chunks: a client that stops reading stops this thread's progress at once (the kernel's
        # own, megabytes on loopback, took seconds to fill under load and hid it from STUCK)
        self.request.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 * COPY_CHUNK)

    def send_head(self):
        status, file = self.resolve()
        if status != 200:
            self.send_error(status, "Bad request" if status == 400 else "Not found")
            return None
        try:
            f = open(file, "rb")  # noqa: SIM115 - closed by copyfile's caller
        except OSError:
            self.send_error(404, "Not found")
            return None
        try:
            size = os.fstat(f.fileno()).st_size
            self.send_response(200)
            self.send_header("Content-Type", self.guess_type(str(file)))
            self.send_header("Content-Length", str(size))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            return f
        except BaseException:
            f.close()
            raise

    def guess_type(self, path):
        return TYPES.get(posixpath.splitext(path)[1].lower(), "application/octet-stream")

    def list_directory(self, path):  # never reached (send_head is overridden); no listings
        self.send_error(404, "Not found")
        return None

    def translate_path(self, path):  # unused by send_head; keep any other caller inside the root
        status, file = self.resolve()
        return str(file) if status == 200 else os.path.join(self.directory, "__refused__")

    def do_POST(self):
        self.send_error(405, "Method not allowed")

    do_PUT = do_DELETE = do_PATCH = do_POST

    def copyfile(self, source, outputfile):
        try:
            while chunk := source.read(COPY_CHUNK):
                outputfile.write(chunk)
                self.server.progressed(self.request)
        except DISCONNECTS:
            self.close_connection = True  # the client went away mid-response: nothing to report

    def log_message(self, format, *args):
        if not self.quiet:
            super().log_message(format, *args)


def waiting_cap() -> int:
    """Connections that may wait on their headers at once: the file-descriptor limit less a reserve for the serving
    threads, their files and the rest of the process."""
    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    soft = 1 << 20 if soft == resource.RLIM_INFINITY else soft
    return max(16, soft - 3 * MAX_CONNECTIONS - 64)


class HeaderReader:
    """One thread reading new connections' request headers without blocking (see the module docstring):
    ``add(sock, address)`` hands it an accepted connection; ``ready(sock, address, head)`` gets each one whose
    headers are complete; :meth:`close` closes the rest."""

    def __init__(self, ready):
        self.ready = ready
        self.selector = selectors.DefaultSelector()
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_w.setblocking(False)
        self.selector.register(self.wake_r, selectors.EVENT_READ)
        self.incoming: list[tuple] = []  # (sock, address), appended by the accepting thread
        self.lock = threading.Lock()
        self.waiting: dict[socket.socket, tuple] = {}  # arrival order -> (address, bytearray, deadline)
        self.stopped = False
        self.thread = threading.Thread(target=self.run, name="omnirecon-view-headers", daemon=True)
        self.thread.start()

    def add(self, sock: socket.socket, address) -> None:
        with self.lock:
            self.incoming.append((sock, address))
        self._wake()

    def _wake(self) -> None:
        try:
            self.wake_w.send(b"\0")
        except OSError:  # the pipe is full (a wake-up is pending anyway) or closed
            pass

    def run(self) -> None:
        while not self.stopped:
            first = next(iter(self.waiting.values()), None)  # the oldest has the earliest deadline
            wait = None if first is None else max(0.0, first[2] - time.monotonic())
            for key, _ in self.selector.select(wait):
                if key.fileobj is self.wake_r:
                    self.wake_r.recv(65536)
                elif key.fileobj in self.waiting:
                    self._read(key.fileobj)
            self._admit()
            now = time.monotonic()
            for sock in [s for s, (_, _, deadline) in self.waiting.items() if deadline <= now]:
                self._drop(sock)

    def _admit(self) -> None:
        with self.lock:
            new, self.incoming = self.incoming, []
        cap = waiting_cap()
        for sock, address in new:
            while len(self.waiting) >= cap:
                self._drop(next(iter(self.waiting)))  # the oldest waiting one makes room
            sock.setblocking(False)
            deadline = time.monotonic() + BundleRequestHandler.timeout  # read when used (tests shorten it)
            self.waiting[sock] = (address, bytearray(), deadline)
            self.selector.register(sock, selectors.EVENT_READ)

    def _read(self, sock: socket.socket) -> None:
        address, head, _ = self.waiting[sock]
        try:
            data = sock.recv(MAX_HEAD)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        head += data
        if not data or len(head) > MAX_HEAD:
            self._drop(sock)
        elif HEAD_END.search(head):
            self.selector.unregister(sock)
            del self.waiting[sock]
            sock.setblocking(True)
            try:
                self.ready(sock, address, bytes(head))
            except (OSError, RuntimeError):  # no thread could start for it: this connection goes, the server stays
                sock.close()

    def _drop(self, sock: socket.socket) -> None:
        self.selector.unregister(sock)
        del self.waiting[sock]
        sock.close()

    def close(self) -> None:
        self.stopped = True
        self._wake()
        self.thread.join(timeout=5)
        for sock in [*self.waiting, *(s for s, _ in self.incoming)]:
            sock.close()
        self.waiting.clear()
        self.selector.close()
        self.wake_r.close()
        self.wake_w.close()


class ViewerServer(http.server.ThreadingHTTPServer):
    """An HTTP server on 127.0.0.1 serving one folder (``port=0``: any free port)."""

    daemon_threads = True
    request_queue_size = 1024  # listen backlog: a burst of connections waits in the kernel, not in SYN retries

    def __init__(self, folder: Path, port: int = 8765, quiet: bool = False):
        self._heads: dict[socket.socket, bytes] = {}  # connections with their headers read, to their serving threads
        self._progress: dict[socket.socket, float] = {}  # served connections -> when their client last took a chunk
        self._lock = threading.Lock()
        folder = Path(folder)
        if not folder.is_dir():
            raise InputError("not a folder", folder, "pass the folder written by `omnirecon export`")
        check_value("port", port)  # the rule: omnirecon/options.py
        self.folder = folder.resolve()
        try:
            super().__init__((HOST, port), partial(BundleRequestHandler, directory=str(self.folder), quiet=quiet))
        except OSError as e:
            raise InputError(f"cannot listen on {HOST}:{port} ({e.strerror or e})", None,
                             "pick another --port, or --port 0 for any free one") from e
        self.reader = HeaderReader(self._serve)

    def process_request(self, request, client_address):
        """An accepted connection goes to the :class:`HeaderReader`, not to a thread."""
        self.reader.add(request, client_address)

    def _serve(self, request, client_address, head: bytes) -> None:
        """A thread for ``request`` whose headers are ``head``, within :data:`MAX_CONNECTIONS` (else a 503)."""
        with self._lock:
            busy = len(self._heads) >= MAX_CONNECTIONS and not self._evict_stuck()
            if not busy:
                self._heads[request] = head
                self._progress[request] = time.monotonic()
        if busy:
            try:
                request.settimeout(0.1)
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
            except OSError:
                pass
            request.close()
            return
        try:
            super().process_request(request, client_address)
        except RuntimeError:  # no thread could start: the slot is free again (the reader closes the connection)
            with self._lock:
                self._heads.pop(request, None)
                self._progress.pop(request, None)
            raise

    def _evict_stuck(self) -> bool:
        """Close the served connection whose client has read nothing for the longest, if that is over :data:`STUCK`
        seconds (its thread's blocked write fails and the thread ends); whether one was closed. Holds the lock."""
        oldest = min(self._progress, key=self._progress.get, default=None)
        if oldest is None or time.monotonic() - self._progress[oldest] < STUCK:
            return False
        del self._heads[oldest], self._progress[oldest]
        try:
            oldest.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        return True

    def progressed(self, request) -> None:
        """The client of ``request`` took another chunk of its file."""
        with self._lock:
            if request in self._progress:
                self._progress[request] = time.monotonic()

    def take_head(self, request) -> bytes:
        """The request line and headers the reader collected for ``request`` (its serving thread reads them)."""
        with self._lock:
            return self._heads[request]

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._lock:
                self._heads.pop(request, None)
                self._progress.pop(request, None)

    def handle_error(self, request, client_address):
        """A client that disconnects (or stalls out) is routine, not an error: no traceback for it."""
        import sys

        if isinstance(sys.exc_info()[1], DISCONNECTS):
            return
        super().handle_error(request, client_address)

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server_address[1]}/"

    def start(self) -> threading.Thread:
        """Serve in a daemon thread (tests, scripts); stop with :meth:`stop`."""
        thread = threading.Thread(target=self.serve_forever, name="omnirecon-view", daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        self.shutdown()
        self.server_close()

    def server_close(self) -> None:
        super().server_close()
        self.reader.close()


def bundle_folder(path: Path) -> Path:
    """The viewer bundle in ``path``: ``path`` itself when it holds ``index.html`` and ``bundle.json``,
    else its ``viewer/`` subfolder (an ``omnirecon export`` output folder). A bundle this version cannot read
    (:func:`~omnirecon.viewer.format.check_bundle`) is refused with one line."""
    path = Path(path)
    for cand in (path, path / "viewer"):
        if (cand / "index.html").is_file() and (cand / "bundle.json").is_file():
            check_bundle(cand)
            return cand
    raise InputError("no viewer bundle here (index.html and bundle.json, or viewer/ holding them)", path,
                     "pass the --out folder of `omnirecon export`")
