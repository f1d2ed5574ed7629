"""Where the built web client and the system Chromium are, for the commands,
the latency benchmark and the browser tests (one definition)."""

from __future__ import annotations

from pathlib import Path

# `npm ci && npm run build` in client_web/ writes here (./dev does it for you).
WEB_ROOT = Path(__file__).resolve().parents[2] / "client_web" / "dist"

# Debian's chromium package; Playwright drives it (its own browser download cannot
# work on these machines).
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = (
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # A page in a headless tab is never "hidden", but keep timers at full rate anyway.
    "--disable-background-timer-throttling",
    "--disable-renderer-backgrounding",
)
