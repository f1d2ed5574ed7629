"""The printed tables of ``upcast bench network``: one row per profile, then (with
``--spectators``) one per spectator."""

from __future__ import annotations

from typing import Any

COLUMNS = (
    ("profile", 10),
    ("fps pub", 8),
    ("fps shown", 10),
    ("ratio", 6),
    ("freezes", 8),
    ("frozen ms", 10),
    ("longest", 8),
    ("g2g p50", 8),
    ("g2g p95", 8),
    ("PSNR", 6),
    ("target", 7),
    ("capacity", 9),
    ("link", 6),
    ("lost/skip/late", 15),
    ("probes", 7),
)


def _num(value: Any, digits: int = 1) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _mbit(value: Any) -> str:
    return "-" if value is None else f"{value / 1e6:.2f}"


def _page(counters: dict[str, Any]) -> str:
    keys = ("framesLost", "groupsSkipped", "late")
    if not any(k in counters for k in keys):
        return "-"
    return "/".join(_num(counters.get(k), 0) for k in keys)


def _probes(probes: dict[str, int] | None) -> str:
    """Link probes in the window: proved / started (``-``: a report without them)."""
    return "-" if probes is None else f"{probes['proved']}/{probes['started']}"


def row(case: dict[str, Any]) -> list[str]:
    freezes = case["freezes"]
    means = case["bitrate_means"]
    capacity = means["capacity_bps"]
    capacity_text = "unlim." if capacity is None else _mbit(capacity)
    return [
        case["name"],
        _num(case["server_fps"]),
        _num(case["page_fps"]),
        _num(case["delivered_ratio"], 2),
        str(freezes["count"]),
        _num(freezes["total_ms"], 0),
        _num(freezes["longest_ms"], 0),
        _num(case["median_ms"]),
        _num(case["p95_ms"]),
        _num(case["received_psnr_db"]["median"]),
        _mbit(means["bitrate_target_bps"]),
        capacity_text,
        _mbit(means["link_delivered_bps"]),
        _page(case["page_counters"]),
        _probes(case.get("probes")),
    ]


def table(cases: list[dict[str, Any]]) -> str:
    head = " ".join(f"{name:>{width}}" for name, width in COLUMNS)
    lines = [
        head,
        " ".join(f"{'':>{w}}" if n != "target" else f"{'Mbit/s':>{w}}" for n, w in COLUMNS),
    ]
    for case in cases:
        cells = row(case)
        lines.append(" ".join(f"{c:>{w}}" for c, (_, w) in zip(cells, COLUMNS, strict=True)))
    return "\n".join(lines)


SPECTATOR_COLUMNS = (
    ("profile", 10),
    ("spectator", 10),
    ("first ms", 9),
    ("fps shown", 10),
    ("ratio", 6),
    ("freezes", 8),
    ("longest", 8),
    ("g2g p50", 8),
    ("g2g p95", 8),
    ("rendition (most s)", 20),
    ("switches", 9),
)


def _rendition(spectator: dict[str, Any]) -> str:
    """The rendition it spent most time on, and its seconds (``-``: the page did not say)."""
    seconds = spectator.get("rendition_seconds")
    if not seconds:
        return "-"
    track, s = max(seconds.items(), key=lambda item: item[1])
    return f"{track} {s:.0f}s"


def spectator_row(profile: str, spectator: dict[str, Any]) -> list[str]:
    freezes = spectator["freezes"]
    return [
        profile,
        spectator["name"],
        _num(spectator["first_picture_ms"], 0),
        _num(spectator.get("page_fps")),
        _num(spectator["delivered_ratio"], 2),
        str(freezes["count"]),
        _num(freezes["longest_ms"], 0),
        _num(spectator["median_ms"]),
        _num(spectator["p95_ms"]),
        _rendition(spectator),
        _num(spectator.get("rendition_switches")),
    ]


def spectator_table(cases: list[dict[str, Any]]) -> str:
    """One row per spectator of each profile's run (the player's link first)."""
    lines = [" ".join(f"{name:>{width}}" for name, width in SPECTATOR_COLUMNS)]
    for case in cases:
        for spectator in case.get("spectators") or []:
            cells = spectator_row(case["name"], spectator)
            lines.append(
                " ".join(f"{c:>{w}}" for c, (_, w) in zip(cells, SPECTATOR_COLUMNS, strict=True))
            )
    return "\n".join(lines)
