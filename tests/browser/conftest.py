"""Fixtures for the browser tests: the built client_web/dist over HTTP, and Chromium.

The pages are served from ``localhost`` (a secure context, like https) so the
browser offers WebTransport and WebCodecs to them.
"""

from __future__ import annotations

import functools
import http.server
import threading
from collections.abc import Iterator

import pytest

from server.ops.browser_paths import WEB_ROOT as DIST


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        pass


@pytest.fixture(scope="module")
def web_root() -> Iterator[str]:
    """Base URL serving client_web/dist."""
    handler = functools.partial(_QuietHandler, directory=str(DIST))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://localhost:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()
