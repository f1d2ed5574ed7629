"""Which rendition a spectator page plays, for ``upcast bench network``.

A spectator picks among the catalog's renditions (``video`` or ``video.N`` for the
player's track, ``video.<W>x<H>`` for the ladder's rungs) and may switch while it plays
(client_web/src/abr.ts). The page's ``stats()`` says which track plays now
(``rendition``), how many times it moved from one to another (``renditionSwitches``)
and the seconds each has played (``renditionSeconds``), all since the page loaded: a
spectator's page is opened at its join, so they cover its whole life. A page without
them (an older build) gives nulls, and is taken to play the catalog's first track.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


def current_rendition(stats: dict[str, Any]) -> str | None:
    """The track the page plays now, if it says."""
    value = stats.get("rendition")
    return value if isinstance(value, str) and value else None


def page_switches(stats: dict[str, Any]) -> int | None:
    value = stats.get("renditionSwitches")
    return int(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def page_seconds(stats: dict[str, Any]) -> dict[str, float] | None:
    """Seconds per rendition as the page counts them, if it does."""
    value = stats.get("renditionSeconds")
    if not isinstance(value, dict) or not all(isinstance(v, int | float) for v in value.values()):
        return None
    return {str(k): round(float(v), 2) for k, v in value.items()}


@dataclass
class RenditionTime:
    """The page's rendition figures as of its latest read."""

    current: str | None = None
    seconds: dict[str, float] | None = None
    switches: int | None = None
    abr: dict[str, Any] | None = None  # the page's ``abr`` (mode, last switch, ...)

    def update(self, stats: dict[str, Any]) -> None:
        # Between two subscriptions the page names none: the last one still counts.
        self.current = current_rendition(stats) or self.current
        self.seconds = page_seconds(stats)
        self.switches = page_switches(stats)
        abr = stats.get("abr")
        self.abr = abr if isinstance(abr, dict) else None

    def summary(self) -> dict[str, Any]:
        return {
            "rendition": self.current,
            "rendition_seconds": self.seconds,
            "rendition_switches": self.switches,
            "abr": self.abr,
        }
