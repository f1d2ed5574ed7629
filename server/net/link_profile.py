"""What an emulated network link does: per-direction rate, delay, jitter, loss, queue.

A ``LinkProfile`` holds one ``Direction`` for the downlink (relay -> viewer) and one
for the uplink (viewer -> relay). A ``Schedule`` is a list of steps, each a profile
that takes over at ``at_s`` seconds after the emulator starts (the ``drop`` and
``blackout`` tests change the link while a stream plays).

Written as a dict (a JSON or TOML schedule file, see server/net/profiles.py), a
profile is either ``{"down": {...}, "up": {...}}`` with the fields of ``Direction``,
or one flat set of those fields that applies both ways: delay, jitter, loss and
reorder to each direction (so RTT = 2 x ``delay_ms``), the rate to the downlink
only, unless ``up_rate_bps`` gives the uplink one (viewers mostly send acks and
input, and a home line's uplink is rarely what limits a stream).

Rates are bit/s: a number, or a string with a unit (``"20mbit"``, ``"512 kbit/s"``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

_UNITS = {"": 1.0, "k": 1e3, "m": 1e6, "g": 1e9}
_RATE_TEXT = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmg]?)(?:bit|bps|b)?(?:/s)?\s*$", re.I)

DEFAULT_QUEUE_MS = 100.0
"""Drop-tail limit when a profile names none: about a home router's buffer at its rate."""


def parse_rate(value: Any) -> Any:
    """``"20mbit"`` -> 20e6; numbers and anything else go on to pydantic's own checks."""
    if not isinstance(value, str):
        return value
    match = _RATE_TEXT.match(value)
    if match is None:
        raise ValueError(f"rate {value!r} is not bit/s: write e.g. 8000000, '8mbit', '512kbit'")
    return float(match.group(1)) * _UNITS[match.group(2).lower()]


Rate = Annotated[float, BeforeValidator(parse_rate), Field(gt=0, allow_inf_nan=False)]
Probability = Annotated[float, Field(ge=0.0, le=1.0)]
Millis = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]


class GilbertElliott(BaseModel):
    """Bursty loss: a two-state Markov chain stepped once per packet.

    In the good state a packet is lost with ``loss_in_good``, in the bad state with
    ``loss_in_bad``; the chain moves good -> bad with ``p_good_to_bad`` and back with
    ``p_bad_to_good``, so a bad spell lasts 1 / ``p_bad_to_good`` packets on average.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    p_good_to_bad: Probability
    p_bad_to_good: Annotated[float, Field(gt=0.0, le=1.0)]
    loss_in_bad: Probability = 1.0
    loss_in_good: Probability = 0.0

    @classmethod
    def from_mean(cls, loss_rate: float, burst_length: float) -> GilbertElliott:
        """The chain whose long-run loss is ``loss_rate`` in bursts of ``burst_length``
        packets on average (every packet in the bad state is lost)."""
        if not 0.0 <= loss_rate < 1.0:
            raise ValueError(f"loss_rate must be in [0, 1), got {loss_rate}")
        if not burst_length >= 1.0:
            raise ValueError(f"burst_length must be >= 1 packet, got {burst_length}")
        p_bad_to_good = 1.0 / burst_length
        # Stationary P(bad) = p_gb / (p_gb + p_bg); set it to loss_rate.
        p_good_to_bad = loss_rate * p_bad_to_good / (1.0 - loss_rate)
        return cls(p_good_to_bad=p_good_to_bad, p_bad_to_good=p_bad_to_good)

    @property
    def mean_loss(self) -> float:
        p_bad = self.p_good_to_bad / (self.p_good_to_bad + self.p_bad_to_good)
        return p_bad * self.loss_in_bad + (1.0 - p_bad) * self.loss_in_good


class Direction(BaseModel):
    """One direction of the link. A packet meets, in order: random and bursty loss,
    the drop-tail queue, serialization at ``rate_bps``, then ``delay_ms`` +- ``jitter_ms``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rate_bps: Rate | None = None
    """Bottleneck rate; None = unlimited (no serialization time, no queue)."""
    delay_ms: Millis = 0.0
    """One-way propagation delay."""
    jitter_ms: Millis = 0.0
    """Each packet's delay is drawn uniformly in delay_ms +- jitter_ms (not below 0).
    Packets still leave in order, as from a real queue, unless ``reorder`` picks them."""
    reorder: Probability = 0.0
    """Chance that a packet skips the delay line and overtakes those in it (netem's reorder)."""
    loss: Probability = 0.0
    """Independent random loss per packet."""
    burst_loss: GilbertElliott | None = None
    """Bursty loss on top of ``loss``."""
    queue_ms: Annotated[float, Field(gt=0.0, allow_inf_nan=False)] = DEFAULT_QUEUE_MS
    """Drop-tail limit as time to drain the queue at ``rate_bps``."""
    queue_bytes: Annotated[int, Field(gt=0)] | None = None
    """Drop-tail limit in bytes; when set it replaces ``queue_ms``."""

    @property
    def queue_limit_s(self) -> float:
        """The queue limit as drain time (infinite for an unlimited rate: no queue forms)."""
        if self.rate_bps is None:
            return math.inf
        if self.queue_bytes is not None:
            return self.queue_bytes * 8.0 / self.rate_bps
        return self.queue_ms / 1000.0

    def describe(self) -> str:
        parts = [f"{self.rate_bps / 1e6:g} Mbit/s" if self.rate_bps else "unlimited"]
        parts.append(f"{self.delay_ms:g} ms")
        if self.jitter_ms:
            parts.append(f"+-{self.jitter_ms:g} ms")
        if self.loss:
            parts.append(f"loss {self.loss:.1%}")
        if self.burst_loss is not None:
            burst = 1.0 / self.burst_loss.p_bad_to_good
            parts.append(f"bursty loss {self.burst_loss.mean_loss:.1%} (bursts ~{burst:g})")
        if self.reorder:
            parts.append(f"reorder {self.reorder:.1%}")
        return ", ".join(parts)


_SHARED_FIELDS = frozenset(Direction.model_fields) - {"rate_bps"}


class LinkProfile(BaseModel):
    """Both directions of the link: ``down`` is relay -> viewer, ``up`` viewer -> relay."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    down: Direction = Direction()
    up: Direction = Direction()

    @model_validator(mode="before")
    @classmethod
    def _one_set_applies_both_ways(cls, data: Any) -> Any:
        if not isinstance(data, dict) or "down" in data or "up" in data:
            return data
        if not data:
            return data
        flat = dict(data)
        up_rate = flat.pop("up_rate_bps", None)
        unknown = sorted(set(flat) - _SHARED_FIELDS - {"rate_bps"})
        if unknown:
            allowed = ", ".join(sorted({*Direction.model_fields, "up_rate_bps", "down", "up"}))
            raise ValueError(f"unknown field(s) {', '.join(unknown)}; allowed: {allowed}")
        shared = {k: v for k, v in flat.items() if k in _SHARED_FIELDS}
        down = dict(shared, rate_bps=flat.get("rate_bps"))
        return {"down": down, "up": dict(shared, rate_bps=up_rate)}

    @classmethod
    def both_ways(
        cls,
        *,
        rate_bps: float | None = None,
        up_rate_bps: float | None = None,
        rtt_ms: float = 0.0,
        jitter_ms: float = 0.0,
        loss: float = 0.0,
        burst_loss: GilbertElliott | None = None,
        reorder: float = 0.0,
        queue_ms: float = DEFAULT_QUEUE_MS,
    ) -> LinkProfile:
        """One set of parameters, as the named profiles are given: half the RTT and the
        jitter/loss each way, ``rate_bps`` on the downlink, ``up_rate_bps`` on the uplink."""
        shared: dict[str, Any] = {
            "delay_ms": rtt_ms / 2.0,
            "jitter_ms": jitter_ms,
            "loss": loss,
            "burst_loss": burst_loss,
            "reorder": reorder,
            "queue_ms": queue_ms,
        }
        return cls(
            down=Direction(rate_bps=rate_bps, **shared),
            up=Direction(rate_bps=up_rate_bps, **shared),
        )

    def describe(self) -> str:
        if self.down == self.up:
            return f"both ways {self.down.describe()}"
        return f"down {self.down.describe()}; up {self.up.describe()}"


class Step(BaseModel):
    """A profile and when it takes over, in seconds after the emulator starts."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    at_s: Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
    profile: LinkProfile

    @model_validator(mode="before")
    @classmethod
    def _inline_profile(cls, data: Any) -> Any:
        # In files the profile's fields sit next to at_s: {"at_s": 10, "rate_bps": "2mbit"}.
        if isinstance(data, dict) and "profile" not in data:
            rest = {k: v for k, v in data.items() if k != "at_s"}
            return {"at_s": data.get("at_s"), "profile": rest}
        return data


class Schedule(BaseModel):
    """Steps in time order; the first starts at 0 and the last lasts for ever."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    steps: tuple[Step, ...] = Field(min_length=1)
    description: str = ""

    @model_validator(mode="before")
    @classmethod
    def _bare_profile(cls, data: Any) -> Any:
        # A file with only a profile's fields is a schedule of one step.
        if isinstance(data, dict) and "steps" not in data:
            description = data.get("description", "")
            profile = {k: v for k, v in data.items() if k != "description"}
            return {"steps": [{"at_s": 0.0, "profile": profile}], "description": description}
        return data

    @model_validator(mode="after")
    def _in_time_order(self) -> Schedule:
        if self.steps[0].at_s != 0.0:
            raise ValueError(f"the first step must start at at_s = 0, not {self.steps[0].at_s}")
        for before, after in zip(self.steps, self.steps[1:], strict=False):
            if after.at_s <= before.at_s:
                raise ValueError(
                    f"steps must be in increasing at_s order: {after.at_s} after {before.at_s}"
                )
        return self

    @classmethod
    def constant(cls, profile: LinkProfile, description: str = "") -> Schedule:
        return cls(steps=(Step(at_s=0.0, profile=profile),), description=description)

    @classmethod
    def of(cls, steps: Iterable[tuple[float, LinkProfile]], description: str = "") -> Schedule:
        """``Schedule.of([(0, cable), (5, dead), (8, cable)])``."""
        return cls(
            steps=tuple(Step(at_s=at, profile=p) for at, p in steps), description=description
        )

    def index_at(self, t_s: float) -> int:
        """The step in force ``t_s`` seconds after the start (step 0 before it)."""
        index = 0
        for i, step in enumerate(self.steps):
            if step.at_s <= t_s:
                index = i
            else:
                break
        return index

    def describe(self) -> str:
        lines = [self.description] if self.description else []
        for step in self.steps:
            lines.append(f"  from {step.at_s:g} s: {step.profile.describe()}")
        return "\n".join(lines)
