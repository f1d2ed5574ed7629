"""Marks for tests that need the system Chromium and the built web client.

Outside CI a missing piece skips with the command that provides it. Under CI
(``.ci/run`` installs Chromium and ``./dev test`` builds the client) nothing is
skipped: a missing piece must fail the run, not hide it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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


def picture_point(page: Any, x: float, y: float) -> tuple[float, float]:
    """Client coordinates of (x, y) in 0..1 of the player canvas's picture (#screen,
    object-fit: contain: letterbox bars excluded)."""
    box = page.locator("#screen").bounding_box()
    w, h = page.evaluate(
        "() => [document.getElementById('screen').width, document.getElementById('screen').height]"
    )
    scale = min(box["width"] / w, box["height"] / h)
    left = box["x"] + (box["width"] - w * scale) / 2
    top = box["y"] + (box["height"] - h * scale) / 2
    return left + x * w * scale, top + y * h * scale
