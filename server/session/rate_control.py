"""The session's video bitrate follows what its player's link carries.

A delay-based controller in the spirit of Google Congestion Control (GCC, the
one WebRTC uses), chosen over BBR-style probing because the stream is a
real-time, mostly app-limited source whose receiver already reports per-frame
arrivals: the queueing delay those arrivals show rises as soon as the encoder
outruns the path, before a buffer overflows, and a frame that waits in a queue
is a frame shown late. BBR needs to probe by overshooting, which for live video
is a visible stall every few seconds.

- **Down fast**: a growing queue (``QUEUE_OVERUSE_MS`` above the path's empty
  delay, still rising, and the last second of frames taking ``STRETCH_OVERUSE``
  times longer to arrive than to be sent) or a high one (``QUEUE_HIGH_MS``), in
  ``OVERUSE_REPORTS`` reports in a row, so a busy page stamping a few frames late
  is not congestion; heavy loss
  (``LOSS_OVERUSE``) or a group the relay had to skip sets the rate to
  ``DECREASE`` times what the viewer actually received over the last second (at
  most ``DECREASE`` times the current rate), at most once per
  ``DECREASE_HOLD_S`` so one congestion episode is one step.
- **Up carefully**: after ``INCREASE_HOLD_S`` without congestion, up by
  ``INCREASE_PER_S`` a second; close to the rate where congestion happened in the
  last ``CONGESTION_MEMORY_S`` (from ``NEAR_BELOW`` under it to GCC's upper bound
  over it, ``near_above``), only by ``ADDITIVE_PER_S`` of that rate a second
  (GCC's near-convergence mode: the link's limit is probably there), never
  above ``PROBE_HEADROOM`` times what the viewer received (an app-limited stream
  cannot prove more) nor the configured bitrate.
- **Probe with padding** (link_probe.py): when that cap, or the careful climb
  while the picture fills less than ``APP_LIMITED`` of the rate, has held the rate
  for ``PROBE_WAIT_S`` (and ``PROBE_AFTER_CUT_S`` after any decrease), every frame
  is padded for a fifth of a second so the path carries a known higher rate; a
  probe that came through raises the cap to its rate for ``PROBE_MEMORY_S`` and
  the rate to ``PROBE_TRUST`` times it, past the careful climb near an old
  congestion point the link has now proved wider than (GCC's probe result). The
  padding rides in the video track, so spectators receive it too.
- **Nothing arrives** (reports without a new frame for a second while we send):
  the safe rate below, then up from there once frames flow.
- **No feedback**: a player that sends input but no feedback (an old page), or
  whose feedback stopped for ``STALE_S`` (its link died, or it lies by silence),
  gets ``SAFE_FRACTION`` of the configured rate until it reports again, unless
  another player reports: then the silent one is served as a spectator. With no
  player at all (spectators only, or nobody) the configured rate stands:
  spectators keep the relay's skip-ahead.

Several players: the lowest rate wins (the encoder serves them all).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from server.session.feedback import FeedbackFields
from server.session.link_estimate import LinkEstimate, LinkSample, SendLog
from server.session.link_probe import PROBE_S, LinkProbe

log = logging.getLogger(__name__)

QUEUE_OVERUSE_MS = 25.0
SILENT = "no feedback"  # the reason of a player held to the safe rate for its silence
QUEUE_HIGH_MS = 80.0
OVERUSE_REPORTS = 2
STRETCH_OVERUSE = 1.03
LOSS_OVERUSE = 0.10  # video frames lost since the last report (not packets: QUIC repairs those)
DECREASE = 0.85
MAX_CUT = 0.5  # one decrease keeps at least half the rate
DECREASE_HOLD_S = 0.5
INCREASE_HOLD_S = 1.0
INCREASE_PER_S = 0.2  # multiplicative, far from the last congestion
ADDITIVE_PER_S = 0.04  # of the rate at the last congestion, per second, near it
NEAR_BELOW = 0.15  # within this fraction below the rate at the last decrease...
NEAR_ABOVE_DEVIATIONS = 3.0  # ...or this many of GCC's deviations above it...
CONGESTION_MEMORY_S = 6.0  # ...which happened less than this long ago
NEAR_DEVIATION_KBPS = 0.4  # GCC's floor of the normalized variance, in kbit/s
PROBE_HEADROOM = 1.5
STALE_S = 2.0
SILENT_PLAYER_S = 3.0  # input without any feedback for this long: an old page
SAFE_FRACTION = 0.25
JOIN_GRACE_S = 3.0  # a skip this soon after a player's first report is its joining
CHANGE_STEP = 0.03  # tell the encoder only about changes larger than this
PROBE_WAIT_S = 0.5  # the climb has been held by what was proven this long: probe
PROBE_AFTER_CUT_S = 1.5  # no probe this soon after a decrease
PROBE_MEMORY_S = 10.0  # what a probe proved raises the cap this long
PROBE_TRUST = 0.9  # the rate jumps to this fraction of what a probe proved
MIN_PROBE_STEP = 1.1  # a probe aims at least this far over the link, or none starts
# The queue a probe builds past a full link is the probe's answer, not congestion: a
# growing queue is no reason to decrease from a probe's start until this long after
# its end. A high one (QUEUE_HIGH_MS, more than a probe builds), losses and skips
# still are: a queue the stream had built before the probe (seen on drop's narrow
# link, 370 ms) must not wait for the probe.
PROBE_DRAIN_S = 1.0
APP_LIMITED = 0.9  # what arrived is under this fraction of the rate: the picture is short


def near_above(congestion_bps: float) -> float:
    """How far above the rate at the last congestion the careful climb goes on:
    GCC's upper bound of its link-capacity estimate, three deviations of
    sqrt(variance x estimate) with the variance at its floor (kbit/s units): 4.7 %
    at 1.6 Mbit/s, 9.5 % at 0.4, 2.4 % at 6. Past it the link has proved wider than
    where it last gave out, and the climb is the quick one again."""
    kbps = congestion_bps / 1000.0
    return NEAR_ABOVE_DEVIATIONS * math.sqrt(NEAR_DEVIATION_KBPS * kbps) * 1000.0


@dataclass
class _Viewer:
    estimate: LinkEstimate = field(default_factory=LinkEstimate)
    first_seen_s: float = 0.0
    last_report_s: float | None = None
    first_report_s: float | None = None
    join_skip_s: float | None = None  # when a skip while joining was reported
    rate: float = 0.0  # this viewer's allowed rate
    last_decrease_s: float = -1e9
    congestion_rate: float | None = None  # the rate at the last decrease
    last_sample: LinkSample | None = None
    decreases: int = 0
    overuse_reports: int = 0  # consecutive reports with a growing queue
    probed_bps: float | None = None  # what the last probe proved, until probed_until_s
    probed_until_s: float = 0.0
    held_since_s: float | None = None  # the climb is held (capped or careful), since

    def proved(self, now_s: float) -> float:
        """What the last probe proved while it still counts (``PROBE_MEMORY_S``), or 0."""
        if self.probed_bps is None or now_s >= self.probed_until_s:
            return 0.0
        return self.probed_bps


@dataclass(frozen=True)
class RateState:
    """What the controller decided, for the timing track, metrics and logs."""

    bitrate: int
    reason: str  # "configured", "no feedback", "congestion", "probing", "steady"
    players: int
    delivered_bps: float | None
    queue_ms: float | None
    probe_bps: float = 0.0  # the rate a running probe pads the stream to


class RateController:
    def __init__(self, ceiling_bps: int, floor_bps: int, *, send_log: SendLog | None = None):
        if floor_bps <= 0 or ceiling_bps < floor_bps:
            raise ValueError(f"need 0 < floor <= ceiling, got {floor_bps} and {ceiling_bps}")
        self.ceiling = float(ceiling_bps)
        self.floor = float(floor_bps)
        self.safe = max(self.floor, self.ceiling * SAFE_FRACTION)
        self.sent = send_log or SendLog()
        self._players: dict[str, _Viewer] = {}
        self._spectators: dict[str, LinkEstimate] = {}
        self._last_update_s: float | None = None
        self._told = float(ceiling_bps)
        self.probe = LinkProbe()
        self._probe_started_s = -1e9
        self.state = RateState(int(ceiling_bps), "configured", 0, None, None)

    # -- what happens -------------------------------------------------------------

    def frame_sent(self, pts_us: int, size: int, now_s: float, padded_to: int = 0) -> None:
        """A frame left: ``size`` bytes on the wire, ``padded_to`` > 0 where the
        encoder padded it for a probe."""
        self.sent.add(pts_us, size, now_s)
        self.probe.frame_sent(pts_us, size, padded_to, now_s)

    def padding_bps(self, now_s: float) -> float:
        """The rate the session should pad every frame to now (0: no probe runs)."""
        return self.probe.padding_bps(now_s)

    def input_seen(self, source: str, now_s: float) -> None:
        """Any input from ``source``: it plays, whether or not it sends feedback."""
        if source not in self._players:
            self._players[source] = _Viewer(first_seen_s=now_s, rate=self._start_rate())
            self._spectators.pop(source, None)

    def feedback(self, source: str, fields: FeedbackFields, now_s: float) -> None:
        if not fields.player and source not in self._players:
            spectator = self._spectators.setdefault(source, LinkEstimate())
            spectator.report(fields, self.sent, now_s)
            return
        self.input_seen(source, now_s)
        viewer = self._players[source]
        viewer.last_report_s = now_s
        if viewer.first_report_s is None:
            viewer.first_report_s = now_s
        viewer.last_sample = viewer.estimate.report(fields, self.sent, now_s)
        self._react(viewer, viewer.last_sample, now_s)
        window = self.probe.base_window_ms()
        if window is not None:
            base = viewer.estimate.least_delay_ms(*window)
            proved = self.probe.report(source, fields.frames, base, now_s)
            if proved is not None:
                self._probed(viewer, proved, now_s)

    def forget(self, source: str) -> None:
        self._players.pop(source, None)
        self._spectators.pop(source, None)

    # -- the decision -------------------------------------------------------------

    def update(self, now_s: float) -> int | None:
        """The rate the encoder should use now, or None when it need not change."""
        dt = 0.0 if self._last_update_s is None else max(0.0, now_s - self._last_update_s)
        self._last_update_s = now_s
        rates = [self._viewer_rate(viewer, now_s, dt) for viewer in self._players.values()]
        # A silent player sets the safe rate only while no player reports: beside one
        # that does, it is served as spectators are (the relay's skip-ahead). A closed
        # tab whose connection lingered (headless Chromium kept one alive until the
        # relay stopped) and a hidden tab whose timers the browser has slowed to one a
        # minute are silent too; each held every player to the safe rate (a quarter of
        # the rate, at half the frame rate) for as long as it stayed.
        heard = [r for r in rates if r[1] != SILENT]
        if heard:
            rates = heard
        if rates:
            rate, reason = min(rates)
        else:
            rate, reason = self.ceiling, "configured"
        self.probe.expire(now_s, list(self._players))
        self._maybe_probe(now_s)
        delivered, queue = self._worst_sample()
        self.state = RateState(
            int(rate), reason, len(self._players), delivered, queue, self.probe.padding_bps(now_s)
        )
        # Small moves wait until they add up, except onto the floor or the ceiling.
        small = abs(rate - self._told) <= CHANGE_STEP * self._told
        if int(rate) == int(self._told) or (small and rate not in (self.floor, self.ceiling)):
            return None
        self._told = rate
        return int(rate)

    def _start_rate(self) -> float:
        # A new player starts where the stream is; the first reports correct it.
        return self._told

    def _viewer_rate(self, viewer: _Viewer, now_s: float, dt: float) -> tuple[float, str]:
        viewer_held_since, viewer.held_since_s = viewer.held_since_s, None
        if viewer.last_report_s is None:
            if now_s - viewer.first_seen_s >= SILENT_PLAYER_S:
                viewer.rate = min(viewer.rate, self.safe)
                return viewer.rate, SILENT
            return viewer.rate, "steady"
        if now_s - viewer.last_report_s >= STALE_S:
            viewer.rate = min(viewer.rate, self.safe)
            return viewer.rate, SILENT
        if now_s - viewer.last_decrease_s < INCREASE_HOLD_S:
            return viewer.rate, "congestion"
        sample = viewer.last_sample
        if sample is None or sample.delivered_bps is None:
            return viewer.rate, "steady"
        last = viewer.congestion_rate
        near = (
            last is not None
            and now_s - viewer.last_decrease_s < CONGESTION_MEMORY_S + INCREASE_HOLD_S
            and (1 - NEAR_BELOW) * last <= viewer.rate <= last + near_above(last)
        )
        step = ADDITIVE_PER_S * last if near and last else INCREASE_PER_S * viewer.rate
        # What arrived allows PROBE_HEADROOM over it (the encoder makes less than it is
        # told); what a probe proved is the link itself, a rate the picture may use
        # whole (a complex moment makes all of its target).
        proven = max(
            PROBE_HEADROOM * sample.delivered_bps + 0.05 * self.ceiling, viewer.proved(now_s)
        )
        target = min(self.ceiling, viewer.rate + step * min(dt, 1.0))
        # Held: by what the link has shown, or to the careful climb near where it last
        # gave out while the picture does not fill the rate (a stream that fills it
        # tests the link itself). Either way only a probe can say it is wider now.
        app_limited = sample.delivered_bps < APP_LIMITED * viewer.rate
        if target > proven or (near and app_limited):
            viewer.held_since_s = now_s if viewer_held_since is None else viewer_held_since
        # An app-limited stream cannot prove more than it sent; never lower it here.
        viewer.rate = max(viewer.rate, min(target, proven))
        return viewer.rate, "probing" if viewer.rate < self.ceiling else "steady"

    def _react(self, viewer: _Viewer, sample: LinkSample, now_s: float) -> None:
        if sample.stalled:
            # Nothing arrives: nothing to measure either. The safe rate until frames
            # flow again (then up from there), not a cut to what "arrived" (zero).
            if viewer.rate > self.safe:
                viewer.rate = self.safe
                viewer.last_decrease_s = now_s
                log.info("rate: %.2f Mbit/s (nothing arrives)", viewer.rate / 1e6)
            return
        joining = viewer.first_report_s is not None and now_s - viewer.first_report_s < JOIN_GRACE_S
        if joining and sample.skipped > 0:
            viewer.join_skip_s = now_s
        # The frames of a group skipped while joining show as lost up to a report later.
        join_loss = viewer.join_skip_s is not None and now_s - viewer.join_skip_s < 1.0
        queue = sample.queue_ms
        slower = sample.stretch is None or sample.stretch > STRETCH_OVERUSE
        growing = queue is not None and queue > QUEUE_OVERUSE_MS and sample.queue_rising and slower
        high = queue is not None and queue > QUEUE_HIGH_MS
        if now_s - self._probe_started_s < PROBE_S + PROBE_DRAIN_S:
            growing = False  # a high queue still counts: the probe alone builds less
        viewer.overuse_reports = viewer.overuse_reports + 1 if growing or high else 0
        congested = (
            viewer.overuse_reports >= OVERUSE_REPORTS
            # Joining, the relay may replay a long cached group (under intra refresh up
            # to SAFETY_IDR_S of video) faster than the viewer's max latency allows and
            # skip it, losing its frames (counted up to a report later): that is the
            # join, not the link.
            or (sample.loss > LOSS_OVERUSE and not join_loss)
            or (sample.skipped > 0 and not joining)
        )
        if not congested or now_s - viewer.last_decrease_s < DECREASE_HOLD_S:
            return
        delivered = sample.delivered_bps
        if delivered is None:
            delivered = sample.reported_bps
        cut = viewer.rate * DECREASE
        if sample.loss > LOSS_OVERUSE:
            # GCC's loss rule: the more is lost, the deeper (86 % lost: 0.57x).
            cut = min(cut, viewer.rate * (1 - 0.5 * sample.loss))
        if delivered is not None:
            cut = min(cut, delivered * DECREASE)
        # At most halve per step (GCC's loss rule at 100 % loss): a report that saw
        # nothing arrive in its quarter second (a reset group) is not a link of zero.
        cut = max(cut, viewer.rate * MAX_CUT)
        # Where the link gave out, for the gentle climb back near it: what arrived,
        # when a growing queue timed it. After a loss, a skip or a cut from what the
        # byte counter says, what arrived is a fraction of the link (frames lost whole,
        # groups reset): no new point. One that a queue timed in the last
        # CONGESTION_MEMORY_S stands (the same episode: the queue it saw overflows
        # into losses and skips a report or two later); erasing it made the climb back
        # the quick one, over the link again (lte without its loss: 3.22 Mbit/s for a
        # queue with 3.78 arriving, 1.99 for the losses 0.75 s later, then 1.99 to
        # 5.8 in 8 s on the 4 Mbit/s link). With none, the climb back is the quick one.
        by_delay = (growing or high) and sample.delivered_bps is not None
        if by_delay:
            viewer.congestion_rate = sample.delivered_bps
        elif now_s - viewer.last_decrease_s >= CONGESTION_MEMORY_S:
            viewer.congestion_rate = None
        viewer.probed_bps = None  # the link gave out: what a probe proved is past
        viewer.rate = max(self.floor, cut)
        viewer.last_decrease_s = now_s
        viewer.decreases += 1
        log.info(
            "rate: %.2f Mbit/s (queue %s ms%s, loss %.0f %%, skipped %d, received %s Mbit/s)",
            viewer.rate / 1e6,
            "?" if queue is None else f"{queue:.0f}",
            ", rising" if sample.queue_rising else "",
            sample.loss * 100,
            sample.skipped,
            "?" if delivered is None else f"{delivered / 1e6:.2f}",
        )

    def _link_bps(self, viewer: _Viewer, now_s: float) -> float:
        """What the viewer's link has shown it carries: the last second's arrivals, or
        a recent probe's proof where that is more."""
        sample = viewer.last_sample
        delivered = sample.delivered_bps if sample is not None else None
        return max(delivered or 0.0, viewer.proved(now_s))

    def _heard(self, now_s: float) -> dict[str, _Viewer]:
        """The players whose reports are fresh, by source."""
        return {
            source: v
            for source, v in self._players.items()
            if v.last_report_s is not None and now_s - v.last_report_s < STALE_S
        }

    def _maybe_probe(self, now_s: float) -> None:
        """Start a probe when the player with the lowest rate has been held (by what
        its link has shown, or near its last congestion) for ``PROBE_WAIT_S``, not
        just after a decrease."""
        if not self._players or not self.probe.idle(now_s):
            return
        heard = self._heard(now_s)
        viewer = min((heard or self._players).values(), key=lambda v: v.rate)
        since = viewer.held_since_s
        if since is None or now_s - since < PROBE_WAIT_S:
            return
        if now_s - viewer.last_decrease_s < PROBE_AFTER_CUT_S or viewer.rate >= self.ceiling:
            return
        link = self._link_bps(viewer, now_s)
        if link <= 0 or min(self.ceiling, self.probe.gain * link) < MIN_PROBE_STEP * link:
            return
        target = self.probe.start(link, self.ceiling, list(heard), now_s)
        self._probe_started_s = now_s
        log.info(
            "rate: probing %.2f Mbit/s (rate %.2f, link shown %.2f)",
            target / 1e6,
            viewer.rate / 1e6,
            link / 1e6,
        )

    def _probed(self, viewer: _Viewer, proved: float, now_s: float) -> None:
        if viewer.last_decrease_s >= self._probe_started_s:
            return  # the probe congested this link: the decrease said what it carries
        viewer.probed_bps = proved
        viewer.probed_until_s = now_s + PROBE_MEMORY_S
        last = viewer.congestion_rate
        if last is not None and proved > last + near_above(last):
            viewer.congestion_rate = None  # the link proved wider than where it gave out
        jump = min(self.ceiling, PROBE_TRUST * proved)
        if jump > viewer.rate:
            viewer.rate = jump
            log.info("rate: %.2f Mbit/s (a probe proved %.2f)", jump / 1e6, proved / 1e6)

    def _worst_sample(self) -> tuple[float | None, float | None]:
        delivered: float | None = None
        queue: float | None = None
        for viewer in self._players.values():
            sample = viewer.last_sample
            if sample is None:
                continue
            got = sample.delivered_bps
            if got is not None:
                delivered = got if delivered is None else min(delivered, got)
            if sample.queue_ms is not None:
                queue = sample.queue_ms if queue is None else max(queue, sample.queue_ms)
        return delivered, queue
