"""Marks for tests that need the system Chromium and the built web client.

Outside CI a missing piece skips with the command that provides it. Under CI
(``.ci/run`` installs Chromium and ``./dev test`` builds the client) nothing is
skipped: a missing piece must fail the run, not hide it.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from server.ops.browser_paths import CHROMIUM


def browser_marks(page: Path) -> list[pytest.MarkDecorator]:
    marks = [pytest.mark.slow]
    if os.environ.get("CI"):
        return marks
    return [
        *marks,
        pytest.mark.skipif(
            not page.exists(),
            reason=f"{page} missing: run `npm ci && npm run build` in client_web",
        ),
        pytest.mark.skipif(
            not CHROMIUM.exists(), reason="no /usr/bin/chromium (apt install chromium)"
        ),
    ]
