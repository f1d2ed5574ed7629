"""The session's rate control over emulated links, end to end.

The real stack (LiveStack: game, worker, session, relay) and a load-test viewer
marked as the player, sending feedback every 250 ms through the network
emulator (its own process, as the network bench runs it). The session's encoder
bitrate is sampled every 100 ms.

- A link that drops below what the stream needs, then comes back: the bitrate
  goes under the new capacity within 2 s, stays under it on average (the climb
  back may pass it by a little: a sawtooth) and back up once the link allows.
- A link that reorders packets and jitters but has room: reordering is not
  congestion, the bitrate stays and the frames arrive.
"""

from __future__ import annotations

import asyncio
import threading
import time

import pytest

from server.bench.latency import LiveStack
from server.bench.network.link import EmulatorProcess
from server.loadtest.plan import RunPlan
from server.loadtest.viewer import ViewerConfig, WorkerResult, run_viewers
from server.net import LinkProfile, Schedule
from server.stack.local import SessionConfig

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

CEILING = 1_500_000
CONFIG = SessionConfig(render_size="320x180", display_size="640x360", fps=30.0)


def _play(
    live: LiveStack, link: EmulatorProcess, seconds: float, samples: list[tuple[float, int]]
) -> WorkerResult:
    """One viewer (the player, with feedback) through the emulator for ``seconds``;
    the session's bitrate sampled meanwhile as (seconds since start, bit/s). The
    link's schedule starts over with the viewer."""
    assert live.session is not None and live.endpoint is not None
    config = ViewerConfig(
        f"http://localhost:{link.port}/",
        live.broadcast,
        live.endpoint.cert_sha256,
        15.0,
        token=live.tokens.player,
        feedback=True,
        player=True,
    )
    link.restart_schedule()
    start = time.monotonic()
    plan = RunPlan(
        start, 15.0, window_start=start, window_end=start + seconds, stop=start + seconds
    )
    done = threading.Event()
    # The rate the session chose (the encoder is told twice that while it thins the
    # frame rate to every other frame).
    state = live.session.stream_state

    def sample() -> None:
        while not done.wait(0.1):
            samples.append((time.monotonic() - start, int(state["bitrate"])))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        return asyncio.run(run_viewers(config, plan, [0], lambda _snap: None))
    finally:
        done.set()
        sampler.join()


def _rates(samples: list[tuple[float, int]], t0: float, t1: float) -> list[int]:
    return [rate for t, rate in samples if t0 <= t < t1]


def test_the_bitrate_follows_a_link_that_narrows_and_widens() -> None:
    wide = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=20)
    narrow = LinkProfile.both_ways(rate_bps=400e3, rtt_ms=20)
    # Free for 4 s (the viewer connects, the stream settles), narrow for 8 s, free.
    schedule = Schedule.of([(0.0, wide), (4.0, narrow), (12.0, wide)])
    samples: list[tuple[float, int]] = []
    with (
        LiveStack(CONFIG, bitrate=CEILING) as live,
        EmulatorProcess(
            listen=("localhost", 0), upstream=("127.0.0.1", live.port), schedule=schedule
        ) as link,
    ):
        result = _play(live, link, 30.0, samples)
        live.check()
    stats = result.stats[0]
    assert stats.error is None and stats.frames > 0, stats.summary()
    before = _rates(samples, 2.0, 4.0)
    # The 2 s after the drop (+0.5 s: the viewer connects after the schedule starts),
    # then the rest of the narrow spell.
    dropping = _rates(samples, 4.0, 6.5)
    narrowed = _rates(samples, 6.5, 12.0)
    widened = _rates(samples, 20.0, 30.0)
    assert before and min(before) == CEILING, before
    assert dropping and min(dropping) < 400e3, dropping
    # The stream fits the narrow link. A cut for loss leaves no congestion point, so
    # the climb back is the quick one and may pass the link again before the spell
    # ends (docs/networks.md, "Links that drop before they queue"; in one CI run it reached
    # 417 kbit/s before 12 s, from a cut that had stopped at 188): a sawtooth under
    # GCC's overshoot, as in the simulation of tests/test_rate_control.py, not a rate
    # that stays over the link.
    assert narrowed and sum(narrowed) / len(narrowed) < 400e3, narrowed
    assert max(narrowed) < 1.25 * 400e3, narrowed
    # Back up once the link allows: the climb is careful near the old congestion point
    # and capped by what arrived until a padding probe proves more, so its pace follows
    # the encoder's output and the probes' timing. A loaded CI run reached 0.49 Mbit/s at
    # 20 s and 1.04 at 24 s (the bar: 1.05), still climbing: 18 s after the link widened
    # is the bound, not 12.
    assert widened and max(widened) > 0.7 * CEILING, widened


def test_reordering_and_jitter_are_not_congestion() -> None:
    shaky = LinkProfile.both_ways(rate_bps=20e6, rtt_ms=30, jitter_ms=8, reorder=0.05)
    samples: list[tuple[float, int]] = []
    with (
        LiveStack(CONFIG, bitrate=CEILING) as live,
        EmulatorProcess(
            listen=("localhost", 0),
            upstream=("127.0.0.1", live.port),
            schedule=Schedule.constant(shaky),
        ) as link,
    ):
        published0 = live.session.broadcast.stats.frames_published if live.session else 0
        result = _play(live, link, 10.0, samples)
        published = (
            live.session.broadcast.stats.frames_published if live.session else 0
        ) - published0
        live.check()
    stats = result.stats[0]
    assert stats.error is None, stats.summary()
    settled = _rates(samples, 3.0, 10.0)
    assert settled and min(settled) >= 0.85 * CEILING, settled
    assert stats.delivery.lost == 0, stats.delivery
    assert stats.frames >= 0.8 * published, (stats.frames, published)
