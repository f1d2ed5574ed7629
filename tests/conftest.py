from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS


@pytest.fixture
def ring_name() -> Iterator[str]:
    """A unique shared-memory name, removed after the test whatever happened."""
    name = f"upcast-test-{os.getpid()}-{uuid.uuid4().hex[:10]}"
    yield name
    for suffix in ("", "-r", "-u"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(f"/dev/shm/{name}{suffix}")


# Module scope, not session: Playwright's sync API keeps an event loop running in
# the main thread while it is open, and later modules call asyncio.run().
@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless system Chromium driven by Playwright (see tests/chromium.py)."""
    from playwright import sync_api

    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            yield browser
        finally:
            browser.close()
