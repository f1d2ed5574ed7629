"""``upcast serve --frame-tap-port``: a session's own frames, as it encoded them, over HTTP.

Off by default: a debugging and testing aid. When on, the session keeps box
thumbnails (1/4 size, server/serve/snapshots.py) of its last frames before
encoding, by frame id, and answers

- ``GET /frames``: ``{"first": ID, "last": ID, "count": N, "factor": 4}`` (JSON);
- ``GET /frames/ID``: that frame's thumbnail as a NumPy ``.npy`` (float32, H/4 x W/4 x 3),
  404 when it is not (or no longer) kept.

A browser's canvas snapshot carries the frame id it shows, so a check outside the
session's process (deploy/smoke.sh, against a container) compares the picture a
viewer got with the frame the server sent, as the in-process tests do. The tap
costs the encoding thread about 2 ms a frame at 1280x720 (the thumbnail).
"""

from __future__ import annotations

import io
import json
import logging
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from server.serve.snapshots import THUMB, FrameThumbs

log = logging.getLogger(__name__)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    thumbs: FrameThumbs


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0].rstrip("/")
        if path == "/frames":
            self._answer(200, "application/json", json.dumps(_summary(self.server.thumbs)).encode())
            return
        head, _, tail = path.rpartition("/")
        if head != "/frames" or not tail.isdigit():
            self._answer(404, "text/plain", b"GET /frames or /frames/<frame id>\n")
            return
        thumb = self.server.thumbs.get(int(tail))
        if thumb is None:
            self._answer(404, "text/plain", f"frame {tail} is not kept\n".encode())
            return
        out = io.BytesIO()
        np.save(out, thumb, allow_pickle=False)
        self._answer(200, "application/octet-stream", out.getvalue())

    def _answer(self, status: int, kind: str, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("frame tap: " + format, *args)  # one line per request is noise at INFO


def _summary(thumbs: FrameThumbs) -> dict[str, int | None]:
    ids = [frame_id for frame_id, _ in thumbs.items()]
    return {
        "first": ids[0] if ids else None,
        "last": ids[-1] if ids else None,
        "count": len(ids),
        "factor": THUMB,
    }


class FrameTapServer:
    """The tap's HTTP side, on its own daemon threads; ``close`` stops it."""

    def __init__(self, thumbs: FrameThumbs, host: str, port: int) -> None:
        server_class = _Server6 if ":" in host else _Server
        self._server: _Server = server_class((host, port), _Handler)
        self._server.thumbs = thumbs
        self.port: int = self._server.server_address[1]
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="frame-tap", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()


def start_frame_tap(thumbs: FrameThumbs, host: str, port: int) -> FrameTapServer | None:
    """The tap on ``host:port``, or None (logged) when the port cannot be had: a debug
    aid never stops the session."""
    try:
        server = FrameTapServer(thumbs, host, port)
    except OSError as exc:
        log.warning("frame tap port %s:%d unavailable: %s", host, port, exc)
        return None
    log.info("frame tap: thumbnails of the encoded frames on http://%s:%d/frames", host, port)
    return server
