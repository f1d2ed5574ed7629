"""The built web client (client_web/dist) loads in headless Chromium without errors.

No relay runs here: both pages must show a clear connecting/failed state and raise
no uncaught exception. Build first: ``cd client_web && npm ci && npm run build``.
"""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Iterator
from typing import Any

from tests.browser.conftest import DIST
from tests.chromium import browser_marks

pytestmark = browser_marks(DIST / "index.html")


def _closed_port_url() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    return f"http://localhost:{port}/"  # nothing listens there any more


@contextlib.contextmanager
def _page(browser: Any, url: str) -> Iterator[tuple[Any, list[str]]]:
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        page.goto(url)
        yield page, errors
    finally:
        page.close()


def test_player_loads_and_reports_failed_connect(web_root: str, browser: Any) -> None:
    relay = _closed_port_url()
    with _page(browser, f"{web_root}/index.html?url={relay}&broadcast=game") as (page, errors):
        page.wait_for_function(
            "() => window.upcast && window.upcast.stats().status.startsWith('failed')",
            timeout=10_000,
        )
        stats = page.evaluate("() => window.upcast.stats()")
        text = page.inner_text("#status")
        snap = page.evaluate("() => window.upcast.snapshot()")
        overlay = page.inner_text("#overlay")
    assert errors == []
    assert text.startswith(("failed", "connecting"))
    assert relay in text
    assert stats["connected"] is False
    assert stats["framesPresented"] == 0
    assert stats["errors"], "the failed connect is recorded"
    assert set(stats["latency"]) >= {"render", "encode", "network", "decode", "present", "total"}
    assert stats["inputPath"].startswith("game/input/")
    assert snap["frameId"] is None and snap["dataUrl"].startswith("data:image/png")
    assert "latency ms" in overlay


def test_watch_page_loads_the_unmodified_element(web_root: str, browser: Any) -> None:
    relay = _closed_port_url()
    with _page(browser, f"{web_root}/watch.html?url={relay}&name=game") as (page, errors):
        page.wait_for_function("() => customElements.get('moq-watch') !== undefined")
        page.wait_for_timeout(1500)
        text = page.inner_text("#status")
        attrs = page.evaluate(
            "() => { const e = document.querySelector('moq-watch');"
            " return [e.getAttribute('url'), e.getAttribute('name')]; }"
        )
    assert errors == []
    assert attrs == [relay, "game"]
    assert relay in text
