"""Probing a player's link with padding, for a stream that sends less than it may.

The rate controller (rate_control.py) may only climb to what the link has shown
it carries, and an app-limited stream shows little: x264 makes 60-70 % of its
target on a calm scene, so after a congestion the climb stops near where the
picture's own bytes left it, however wide the link has become. WebRTC's answer
is the one taken here (the probe clusters Google Congestion Control sends when
the application is limited): for a short while send a known, higher rate with
padding, watch how it arrives, and trust the link up to that rate if it came
through.

A probe makes every frame for ``PROBE_S`` at least ``target / fps`` bytes with
H.264 filler data (server/media/filler.py), so the path carries ``target``
whatever the picture needs. The player already reports when each frame's last
byte arrived; the session knows when it sent it, so each frame has a one-way
delay (up to a constant clock offset). A path that carries the target delivers
every probe frame before the next one leaves, so the probe's frames all see the
same delay; a narrower path queues the surplus and the delay grows frame after
frame (at 0.85 times the target, by 18 ms from the first two of five frames to
the last two at 30 fps). A probe is *proved* when every one of its frames
arrived, all but one were delayed no more than ``SLACK_MS`` over the first two
(on ``lte``, comparing only the last two with the first two proved 4.7 and 4.9
Mbit/s of a 4 Mbit/s link: bursty loss holds single frames back at random), and
the first two no more than a frame interval plus ``SLACK_MS`` over the least
delay of the frames sent in the ``BASE_S`` before the probe (carried()): on
``lte`` a start held behind a lost packet (a retransmission, 60 ms) had hidden the
growth after it and proved 4.7 Mbit/s of a 4 Mbit/s link.

The delay trend, not the spread of the arrivals, decides: the spread can be
squeezed by a frame held behind a lost packet or stamped late by a busy page,
and then proves a rate the link never carried (on ``lte`` it proved 5.6 Mbit/s
of a 4 Mbit/s link).

Short on purpose: a probe past a narrow link builds a queue of about
``PROBE_S x (target / capacity - 1)``: 50 ms at the first probe's gain on a link
the stream already fills. A probe that proved its target is followed by one at
``NEXT_GAIN`` over it (2.0, as WebRTC, brought the rate back a second sooner
after a step up in the simulation of tests/test_rate_control.py, but lost five
times as many frames on the narrow link before it); one that did not waits
``RETRY_S`` and starts again at ``FIRST_GAIN``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

PROBE_S = 0.2  # six frames at 30 fps
FIRST_GAIN = 1.25  # over what the link has shown, after a failed probe (or none)
NEXT_GAIN = 1.5  # after a probe that proved its target
SLACK_MS = 15.0  # delay variation a carried probe may still show (jitter, stamping)
AGAIN_S = 0.5  # after a success, the next probe may start this soon
RETRY_S = 4.0  # after a failure
RESULT_TIMEOUT_S = 2.0  # after the probe's end, a frame not reported counts as lost
MIN_FRAMES = 5
BASE_S = 2.0  # the path's delay before a probe: the least of the frames sent this long before
MAX_PROBE_S = 0.5  # a stream too slow for MIN_FRAMES in this long is not probed further


@dataclass
class _Frame:
    size: int
    sent_ms: float


@dataclass
class Probe:
    """One probe: the frames it padded and when each viewer got them."""

    target_bps: float
    started_s: float
    ends_s: float
    frames: dict[int, _Frame] = field(default_factory=dict)  # pts -> what was sent
    arrivals: dict[str, dict[int, float]] = field(default_factory=dict)  # viewer -> pts -> ms
    results: dict[str, bool] = field(default_factory=dict)  # viewer -> proved

    def interval_ms(self) -> float:
        sent = sorted(f.sent_ms for f in self.frames.values())
        return (sent[-1] - sent[0]) / (len(sent) - 1) if len(sent) > 1 else 0.0

    def running(self, now_s: float) -> bool:
        """Padding goes on for ``PROBE_S``, longer at a low frame rate until it padded
        ``MIN_FRAMES`` frames, never past ``MAX_PROBE_S``."""
        if now_s >= self.started_s + MAX_PROBE_S:
            return False
        return now_s < self.ends_s or len(self.frames) < MIN_FRAMES


def carried(probe: Probe, arrivals: dict[int, float], base_delay_ms: float | None) -> bool:
    """Every frame of the probe arrived; all but one were delayed no more than
    ``SLACK_MS`` over the lesser of the first two (a path slower than the probe
    queues a little more of each frame, so at least the last two grow; one frame
    stamped late by a busy page or held behind a lost packet may stand out); and the
    first two no more than a frame interval plus ``SLACK_MS`` over
    ``base_delay_ms``, the path's least delay before the probe (a start held behind
    a lost packet hides the growth after it)."""
    if base_delay_ms is None or len(probe.frames) < MIN_FRAMES:
        return False
    if any(pts not in arrivals for pts in probe.frames):
        return False
    delays = [arrivals[pts] - probe.frames[pts].sent_ms for pts in sorted(probe.frames)]
    start = min(delays[:2])
    all_but_one = sorted(delays)[-2]
    return (
        all_but_one - start <= SLACK_MS and start - base_delay_ms <= probe.interval_ms() + SLACK_MS
    )


def describe(probe: Probe, arrivals: dict[int, float], base_delay_ms: float | None) -> str:
    """The probe's frames for the log: how many arrived, and each one's delay over
    the path's before the probe (``?``: unknown)."""
    delays = []
    for pts in sorted(probe.frames):
        if pts not in arrivals or base_delay_ms is None:
            delays.append("?")
        else:
            delays.append(f"{arrivals[pts] - probe.frames[pts].sent_ms - base_delay_ms:+.0f}")
    sizes = sorted(f.size for f in probe.frames.values())
    size = f"{sizes[0] // 1000}-{sizes[-1] // 1000} kB" if sizes else "none"
    over = " ".join(delays)
    return f"{len(probe.frames)} frames of {size}, delay over the path's before (ms): {over}"


class LinkProbe:
    """The session's probes: when the next may start, at what gain, and their results."""

    def __init__(self) -> None:
        self.current: Probe | None = None
        self.gain = FIRST_GAIN
        self.next_s = 0.0
        self.started = 0
        self.succeeded = 0

    def padding_bps(self, now_s: float) -> float:
        """The rate every frame is padded to now, 0 when no probe runs."""
        probe = self.current
        return probe.target_bps if probe is not None and probe.running(now_s) else 0.0

    def idle(self, now_s: float) -> bool:
        """No probe runs or awaits results, and the next one may start."""
        return self.current is None and now_s >= self.next_s

    def start(self, link_bps: float, ceiling_bps: float, players: list[str], now_s: float) -> float:
        """Probe at ``gain`` times what the link has shown (``link_bps``)."""
        target = min(ceiling_bps, self.gain * link_bps)
        probe = Probe(target, now_s, now_s + PROBE_S)
        probe.arrivals = {p: {} for p in players}
        self.current = probe
        self.started += 1
        return target

    def frame_sent(self, pts_us: int, size: int, padded_to: int, now_s: float) -> None:
        """A frame left; ``padded_to`` > 0: the encoder padded it for the probe."""
        probe = self.current
        # Padded frames encoded after the probe's end (the encoder hears of it at the
        # next update) still go out, after the cluster: they are not part of it.
        if probe is not None and padded_to > 0 and probe.running(now_s):
            probe.frames[pts_us] = _Frame(size, now_s * 1000)

    def report(
        self,
        source: str,
        frames: list[tuple[int, float]],
        base_delay_ms: float | None,
        now_s: float,
    ) -> float | None:
        """A viewer's arrivals (``base_delay_ms``: its least delay before the probe,
        see base_window_ms()); returns the rate the probe proved for it once that is
        known (None: not yet, or nothing)."""
        probe = self.current
        if probe is None or source not in probe.arrivals or source in probe.results:
            return None
        seen = probe.arrivals[source]
        for pts, arrival_ms in frames:
            if pts in probe.frames and pts not in seen:
                seen[pts] = arrival_ms
        complete = not probe.running(now_s) and len(seen) == len(probe.frames) > 0
        if not complete and now_s < probe.started_s + MAX_PROBE_S + RESULT_TIMEOUT_S:
            return None
        proved = carried(probe, seen, base_delay_ms)
        probe.results[source] = proved
        log.info(
            "probe %.2f Mbit/s to %s: %s (%s)",
            probe.target_bps / 1e6,
            source,
            "proved" if proved else "not proved",
            describe(probe, seen, base_delay_ms),
        )
        self._maybe_finish(now_s)
        return probe.target_bps if proved else None

    def base_window_ms(self) -> tuple[float, float] | None:
        """The send times (ms, our clock) of the frames whose least delay is the path's
        before the running probe: the ``BASE_S`` before it."""
        probe = self.current
        if probe is None:
            return None
        return (probe.started_s - BASE_S) * 1000, probe.started_s * 1000

    def expire(self, now_s: float, players: list[str]) -> None:
        """Viewers that left or never answered count as a failed probe once it timed out."""
        probe = self.current
        if probe is None:
            return
        for source in list(probe.arrivals):
            if source not in players:
                probe.arrivals.pop(source)
        if now_s >= probe.started_s + MAX_PROBE_S + RESULT_TIMEOUT_S:
            for source in probe.arrivals:
                probe.results.setdefault(source, False)
        self._maybe_finish(now_s)

    def _maybe_finish(self, now_s: float) -> None:
        probe = self.current
        if probe is None or any(s not in probe.results for s in probe.arrivals):
            return
        self.current = None
        if probe.results and all(probe.results.values()):
            self.succeeded += 1
            self.gain = NEXT_GAIN
            self.next_s = now_s + AGAIN_S
        else:
            self.gain = FIRST_GAIN
            self.next_s = now_s + RETRY_S
