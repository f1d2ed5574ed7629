"""Fixtures for the browser tests: the built client_web/dist over HTTP, and Chromium.

The pages are served from ``localhost`` (a secure context, like https) so the
browser offers WebTransport and WebCodecs to them.
"""

from __future__ import annotations

import functools
import http.server
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.bench.latency import CHROMIUM, CHROMIUM_ARGS

DIST = Path(__file__).resolve().parents[2] / "client_web" / "dist"


def needs(path: Path) -> list[pytest.MarkDecorator]:
    """Marks for a browser test module that loads ``path`` from the build."""
    return [
        pytest.mark.slow,
        pytest.mark.skipif(
            not path.exists(),
            reason="client_web/dist missing: run `npm ci && npm run build` in client_web",
        ),
        pytest.mark.skipif(not CHROMIUM.exists(), reason="no /usr/bin/chromium"),
    ]


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


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            yield browser
        finally:
            browser.close()
