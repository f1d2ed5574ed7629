from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS
from server.session.quality.calibrate import CACHE_ENV

# Sessions started by the tests (and the processes they start) read no calibration a
# developer made on this machine (`upcast calibrate`): every run starts from the shipped
# table, as on a fresh CI machine. A test that wants one writes it under its own dir.
os.environ[CACHE_ENV] = os.path.join(
    os.environ.get("TMPDIR", "/tmp"), f"upcast-test-cache-{os.getpid()}"
)


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
