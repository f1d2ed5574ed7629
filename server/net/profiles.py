"""Named link schedules (issue 21) and schedule files; ``resolve`` takes either.

Named (RTT split evenly between the two directions; rates are the downlink's,
the uplink is unlimited; every rate-limited link drops beyond ~100 ms of queue):

- ``lan``: unlimited, no delay.
- ``cable``: 20 Mbit/s, 15 ms RTT.
- ``wifi``: 8 Mbit/s, 30 ms RTT, +-5 ms jitter each way (RTT 30 +- 10 ms),
  1 % random loss each way.
- ``lte``: 4 Mbit/s, 60 ms RTT, 2 % bursty loss each way in bursts of 3 packets
  on average (Gilbert-Elliott).
- ``drop``: 20 Mbit/s, 2 Mbit/s from 10 s, 20 Mbit/s again from 20 s; 20 ms RTT.
- ``blackout``: cable, then 100 % loss both ways from 5 s to 8 s, then cable.

A schedule file is JSON (``.json``) or TOML (``.toml``). Either one profile:

    {"rate_bps": "8mbit", "delay_ms": 15, "jitter_ms": 5, "loss": 0.01}

or steps, each a profile's fields next to ``at_s`` (seconds after the start; the
first step at 0, the last lasts for ever):

    description = "a 2 s dip to 1 Mbit/s"
    [[steps]]
    at_s = 0
    rate_bps = "10mbit"
    delay_ms = 10
    [[steps]]
    at_s = 5
    rate_bps = "1mbit"
    delay_ms = 10
    [[steps]]
    at_s = 7
    rate_bps = "10mbit"
    delay_ms = 10

Profile fields, one flat set applied both ways (the rate to the downlink only):
``rate_bps`` (number or "20mbit"/"512kbit"; absent = unlimited), ``up_rate_bps``,
``delay_ms`` (one way), ``jitter_ms``, ``loss`` (0..1), ``reorder`` (0..1),
``burst_loss`` ({p_good_to_bad, p_bad_to_good, loss_in_bad=1, loss_in_good=0}),
``queue_ms`` (default 100) or ``queue_bytes``. Or per direction:
``{"down": {...}, "up": {...}}`` with the same fields except ``up_rate_bps``.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

from pydantic import ValidationError

from server.net.link_profile import GilbertElliott, LinkProfile, Schedule

_CABLE = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=15.0)
_DEAD_CABLE = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=15.0, loss=1.0)


def _drop_at(rate_bps: float) -> LinkProfile:
    return LinkProfile.both_ways(rate_bps=rate_bps, rtt_ms=20.0)


PROFILES: dict[str, Schedule] = {
    "lan": Schedule.constant(LinkProfile(), "unlimited, no delay"),
    "cable": Schedule.constant(_CABLE, "20 Mbit/s, 15 ms RTT"),
    "wifi": Schedule.constant(
        LinkProfile.both_ways(rate_bps=8e6, rtt_ms=30.0, jitter_ms=5.0, loss=0.01),
        "8 Mbit/s, 30 ms RTT +- 10 ms, 1 % random loss",
    ),
    "lte": Schedule.constant(
        LinkProfile.both_ways(
            rate_bps=4e6, rtt_ms=60.0, burst_loss=GilbertElliott.from_mean(0.02, 3.0)
        ),
        "4 Mbit/s, 60 ms RTT, 2 % loss in bursts of ~3 packets",
    ),
    "drop": Schedule.of(
        [(0.0, _drop_at(20e6)), (10.0, _drop_at(2e6)), (20.0, _drop_at(20e6))],
        "20 -> 2 -> 20 Mbit/s in 10 s steps, 20 ms RTT",
    ),
    "blackout": Schedule.of(
        [(0.0, _CABLE), (5.0, _DEAD_CABLE), (8.0, _CABLE)],
        "cable, 3 s of 100 % loss from 5 s, then cable again",
    ),
}


class ProfileError(ValueError):
    """A profile name that is not known, or a schedule file that cannot be used."""


def load_schedule(path: Path) -> Schedule:
    """A schedule from a .json or .toml file; ProfileError says which field is wrong."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProfileError(f"cannot read {path}: {exc.strerror}") from exc
    try:
        if path.suffix.lower() == ".toml":
            data = tomllib.loads(text)
        elif path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            raise ProfileError(f"{path}: a schedule file ends in .json or .toml")
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ProfileError(f"{path}: not valid {path.suffix[1:].upper()}: {exc}") from exc
    try:
        return Schedule.model_validate(data)
    except ValidationError as exc:
        problems = "\n".join(
            f"  {'.'.join(str(p) for p in err['loc']) or '(root)'}: {err['msg']}"
            for err in exc.errors(include_url=False)
        )
        raise ProfileError(f"invalid schedule in {path}:\n{problems}") from exc


def resolve(name_or_path: str) -> Schedule:
    """A named profile (``cable``) or the schedule in a file (``./dip.toml``)."""
    if name_or_path in PROFILES:
        return PROFILES[name_or_path]
    path = Path(name_or_path)
    if path.suffix.lower() in (".json", ".toml") or path.exists():
        return load_schedule(path)
    names = ", ".join(PROFILES)
    raise ProfileError(
        f"unknown profile {name_or_path!r}: use one of {names} or a .json/.toml schedule file"
    )
