"""The relay under attack over real QUIC, with good viewers watching at the same time.

Each test runs one event loop: a Relay on port 0 (tests/relay_harness.py), a publisher
streaming 30 fps, three good viewers from 127.0.0.1, and one scenario of
server/bench/adversary/scenarios.py attacking from 127.0.0.2 for a second or two. It
asserts what the issue "no unauthenticated client can starve the viewers" asks: the
viewers keep >= 60 % of the frames they got just before the attack, the attacker is
closed (floods: within 1 s of crossing the limit) or refused, the refusal is counted,
the relay's other sessions are untouched and nothing is logged at ERROR.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server.auth import Authorizer, generate_key, load_key
from server.auth.keys import AuthKey
from server.auth.minting import session_tokens
from server.bench.adversary.attack_types import (
    GUARD,
    SKIPPED,
    AttackContext,
    AttackResult,
    Expectation,
)
from server.bench.adversary.client import (
    FRAME_HEADERS,
    FRAME_SETTINGS,
    MAX_VARINT,
    UNI_CONTROL,
    Target,
    count_still_served,
    frame_header,
    open_attack,
)
from server.bench.adversary.h3 import GREASE_FRAME, STREAM_KINDS, send_garbage
from server.bench.adversary.scenarios import SCENARIOS
from server.moq.errors import ErrorCode
from server.quic.certs import CertBundle, generate_cert
from server.quic.connection import IDLE_TIMEOUT_S
from server.quic.guard import GuardLimits
from server.relay.relay import Relay
from tests.relay_harness import Publisher, connected_viewers, running_relay, until

FPS = 30.0
GOOD_VIEWERS = 3
BASELINE_S = 1.0
ATTACK_S = 2.0
# The attacker, the relay and the good viewers share this process's one event loop and
# 2 cores, so the attacker's own work shows in the viewers' frame counts: two fresh-clone
# CI runs saw 22 of 30 frames (73 %) once each with nothing starving. A starved relay (the
# HEADERS flood before the guard) left them 29 %. The 95 % criterion is the benchmark's
# (`upcast bench adversary`: viewers, relay and attacker in separate processes).
KEEP_FRACTION = 0.6
CLOSE_WITHIN_S = 1.0
# Tighter than the defaults so that a test waits a second, not five.
TEST_GUARD = GuardLimits(connect_deadline_s=1.0)
H3_PARSE_ERRORS = {0x105, 0x106}  # H3_FRAME_UNEXPECTED, H3_FRAME_ERROR
JWT_SHAPED = re.compile(r"eyJ[A-Za-z0-9_-]{4,}\.[A-Za-z0-9_-]{4,}")


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


@pytest.fixture(scope="module")
def key(tmp_path_factory: pytest.TempPathFactory) -> AuthKey:
    path = tmp_path_factory.mktemp("key") / "relay.jwk"
    generate_key(path)
    return load_key(path)


@pytest.fixture(autouse=True)
def no_relay_errors(caplog: pytest.LogCaptureFixture) -> Any:
    """Whatever the attacker does, nothing in the relay logs an error (an exception
    that escaped into a handler is logged at ERROR by the adapters)."""
    caplog.set_level(logging.WARNING)
    yield
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]


def run(coro: Coroutine[Any, Any, None], timeout: float = 40.0) -> None:
    async def bounded() -> None:
        loop = asyncio.get_running_loop()
        escaped: list[str] = []
        loop.set_exception_handler(lambda _, context: escaped.append(str(context)))
        async with asyncio.timeout(timeout):
            await coro
        assert not escaped, escaped

    asyncio.run(bounded())


def sample(relay: Relay, expectation: Expectation) -> float:
    relay._update_counters()  # counters the stats loop adds once a second
    if not expectation.reasons:
        return relay.registry.get_sample_value(expectation.metric) or 0.0
    return sum(
        relay.registry.get_sample_value(expectation.metric, {"reason": r}) or 0.0
        for r in expectation.reasons
    )


@dataclass
class Outcome:
    relay: Relay
    result: AttackResult
    baseline: list[int]  # frames each good viewer got in BASELINE_S before the attack
    during: list[int]  # ... and during the attack, scaled to BASELINE_S
    moved: dict[str, float] = field(default_factory=dict)  # expectation -> delta
    good_links_kept: bool = True
    publisher_frames: int = 0

    def assert_viewers_kept_up(self) -> None:
        for before, during in zip(self.baseline, self.during, strict=True):
            assert during >= KEEP_FRACTION * before, (self.baseline, self.during)

    def assert_counted(self, *expectations: Expectation) -> None:
        for e in expectations:
            assert self.moved[e.describe()] > 0, f"{e.describe()} did not move: {self.moved}"


Attack = Callable[[AttackContext, float], Awaitable[AttackResult]]


async def under_attack(
    cert: CertBundle,
    attack: Attack,
    *,
    duration_s: float = ATTACK_S,
    expects: tuple[Expectation, ...] = (),
    key: AuthKey | None = None,
    group_every: int = 15,
    settle_s: float = 0.0,
    after: Callable[[Relay, AttackResult], Awaitable[None]] | None = None,
    **config: Any,
) -> Outcome:
    """Relay + publisher + good viewers; baseline, then the attack; the measurements."""
    config.setdefault("guard", TEST_GUARD)
    authorizer = Authorizer(key) if key is not None else Authorizer.open_relay()
    async with running_relay(cert, authorizer=authorizer, **config) as relay:
        publisher = Publisher()
        token = session_tokens(key, "game").publisher if key is not None else None
        await publisher.start(relay.port, cert, token)
        await until(lambda: "game" in relay.core.broadcasts)
        viewers = await connected_viewers(relay.port, cert, GOOD_VIEWERS)
        for viewer in viewers:
            await viewer.subscribed()
        good_links = dict(relay.links)
        total = int(FPS * (BASELINE_S + duration_s + settle_s + 30))
        streaming = asyncio.create_task(publisher.stream(total, fps=FPS, group_every=group_every))
        try:
            await asyncio.sleep(0.3)
            counts = [len(v.frames) for v in viewers]
            await asyncio.sleep(BASELINE_S)
            baseline = [len(v.frames) - c for v, c in zip(viewers, counts, strict=True)]
            before = {e.describe(): sample(relay, e) for e in expects}
            ctx = AttackContext(Target("127.0.0.1", relay.port, cert.sha256_hex), auth_key=key)
            counts = [len(v.frames) for v in viewers]
            t0 = time.monotonic()
            result = await attack(ctx, duration_s)
            # An attack the relay ends at once (closed after 64 streams: 0.1 s) would
            # leave a window of two or three frames, scaled up to a second: one frame
            # late and a viewer "kept" 7 of 30 (a fresh-clone CI run). Count a full
            # second from the attack's start at least, the aftermath included.
            await asyncio.sleep(max(0.0, BASELINE_S - (time.monotonic() - t0)))
            elapsed = time.monotonic() - t0
            during = [
                round((len(v.frames) - c) * BASELINE_S / elapsed)
                for v, c in zip(viewers, counts, strict=True)
            ]
            if after is not None:
                await after(relay, result)
            await asyncio.sleep(settle_s)
            moved = {e.describe(): sample(relay, e) - before[e.describe()] for e in expects}
            kept = all(
                relay.links.get(conn_id) is link and not link.closed
                for conn_id, link in good_links.items()
            )
            return Outcome(relay, result, baseline, during, moved, kept, publisher.number)
        finally:
            streaming.cancel()
            for viewer in viewers:
                viewer.close()
            publisher.close()


def scenario_test(
    cert: CertBundle, name: str, **options: Any
) -> Outcome:  # runs one named scenario with its own expectations
    scenario = SCENARIOS[name]
    options.setdefault("expects", scenario.expects)
    holder: list[Outcome] = []

    async def main() -> None:
        holder.append(await under_attack(cert, scenario.run, **options))

    run(main())
    return holder[0]


def assert_common(outcome: Outcome) -> None:
    outcome.assert_viewers_kept_up()
    assert outcome.good_links_kept, "a good viewer's or the publisher's session was touched"


# -- HTTP/3 floods -------------------------------------------------------------------

LENGTH_FLOODS = ["headers_flood", "settings_flood"]
BYTE_FLOODS = [
    "unknown_frame_flood",
    "control_unknown_flood",
    "unknown_uni_flood",
    "qpack_encoder_flood",
]


@pytest.mark.parametrize("name", LENGTH_FLOODS)
def test_frame_length_flood_is_closed_within_a_second(cert: CertBundle, name: str) -> None:
    """A frame header that claims 2^62-1 bytes crosses max_frame_bytes at once."""
    outcome = scenario_test(cert, name)
    assert_common(outcome)
    result = outcome.result
    assert result.closed_at is not None, "the flooding connection was never closed"
    delay = result.close_delay_s
    assert delay is not None and delay <= CLOSE_WITHIN_S, delay
    assert result.open_at_end == 0
    outcome.assert_counted(*SCENARIOS[name].expects)


def crossing_time(result: AttackResult, limits: GuardLimits) -> float | None:
    """When the first connection's bytes passed the smallest byte limit that applies:
    the stream-buffer and pre-CONNECT bounds, or the overhead bucket's burst plus what
    its rate refilled since the first byte."""
    if not result.sent_log:
        return None
    start = result.sent_log[0][0]
    fixed = min(limits.max_stream_buffer_bytes, limits.max_pre_connect_bytes)
    for t, n in result.sent_log:
        bucket = limits.overhead_burst_bytes + limits.overhead_bytes_per_s * (t - start)
        if n > min(fixed, bucket):
            return t
    return None


@pytest.mark.parametrize("name", BYTE_FLOODS)
def test_byte_flood_is_closed_within_a_second_of_its_limit(cert: CertBundle, name: str) -> None:
    outcome = scenario_test(cert, name)
    assert_common(outcome)
    result = outcome.result
    assert result.closed_at is not None, "the flooding connection was never closed"
    crossed = crossing_time(result, TEST_GUARD)
    # Closed before any byte limit was crossed (another bound caught it) is fine too.
    if crossed is not None:
        assert result.closed_at - crossed <= CLOSE_WITHIN_S, result.closed_at - crossed
    assert result.open_at_end == 0
    outcome.assert_counted(*SCENARIOS[name].expects)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["headers", "settings", "unknown_request", "unknown_control"]),
    length=st.integers(min_value=TEST_GUARD.max_frame_bytes + 1, max_value=MAX_VARINT),
)
def test_random_oversized_frame_length_is_refused(cert: CertBundle, kind: str, length: int) -> None:
    """Any frame length past the limit, on any stream that carries HTTP/3 frames, ends the
    connection (quickly for the frame types with a bound, by bytes for the others)."""

    async def attack(ctx: AttackContext, duration_s: float) -> AttackResult:
        result = AttackResult(f"oversized_{kind}")
        conn = await open_attack(ctx.target, h3=kind != "settings")
        result.connections = 1
        if kind == "headers":
            stream_id = conn.open_bidi()
            conn.send(stream_id, frame_header(FRAME_HEADERS, length))
        elif kind == "settings":
            stream_id = conn.open_uni(UNI_CONTROL)
            conn.send(stream_id, frame_header(FRAME_SETTINGS, length))
        elif kind == "unknown_request":
            stream_id = conn.open_bidi()
            conn.send(stream_id, frame_header(GREASE_FRAME, length))
        else:
            stream_id = conn.h3.control_stream_id
            conn.send(stream_id, frame_header(GREASE_FRAME, length))
        result.crossed_at = time.monotonic()
        deadline = time.monotonic() + duration_s
        while not conn.is_closed and time.monotonic() < deadline:
            if conn.buffered(stream_id) < 64 * 1024:
                conn.send(stream_id, bytes(8 * 1200))
            conn.flush()
            await asyncio.sleep(0.005)
        result.record_close(conn, first=True)
        result.open_at_end = await count_still_served([conn])
        conn.vanish()
        return result

    guard = (Expectation(GUARD, tuple(_guard_reasons())),)
    holder: list[Outcome] = []

    async def main() -> None:
        holder.append(await under_attack(cert, attack, duration_s=1.5, expects=guard))

    run(main())
    outcome = holder[0]
    assert_common(outcome)
    assert outcome.result.open_at_end == 0, f"{kind} of length {length} was never closed"
    if kind.startswith("unknown") and set(outcome.result.close_codes) & H3_PARSE_ERRORS:
        # An unknown frame is discarded, whatever its length; once it ends, the zeros
        # that follow are DATA frames before any HEADERS (or on the control stream),
        # which aioquic's HTTP/3 layer refuses itself before a byte limit is reached.
        return
    outcome.assert_counted(*guard)


def _guard_reasons() -> list[str]:
    from server.quic.guard import REASONS

    return list(REASONS)


# -- garbage on every stream kind ------------------------------------------------------


@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    attacks=st.lists(
        st.tuples(st.sampled_from(STREAM_KINDS), st.binary(min_size=1, max_size=1500)),
        min_size=1,
        max_size=len(STREAM_KINDS),
    )
)
def test_random_bytes_on_any_stream_kind_harm_no_one_else(
    cert: CertBundle, attacks: list[tuple[str, bytes]]
) -> None:
    async def attack(ctx: AttackContext, duration_s: float) -> AttackResult:
        result = AttackResult("garbage")
        conns = []
        for kind, data in attacks:
            conns.append(await send_garbage(ctx, kind, data))
            result.connections += 1
        await asyncio.sleep(0.5)
        for conn in conns:
            result.record_close(conn, first=False)
            conn.vanish()
        return result

    holder: list[Outcome] = []

    async def main() -> None:
        holder.append(await under_attack(cert, attack, duration_s=0.0))

    run(main())
    assert holder[0].good_links_kept


def test_garbage_connections_end_by_the_connect_deadline(cert: CertBundle) -> None:
    """Garbage on streams the relay ignores closes nothing by itself; the connect
    deadline (1 s here) still ends every connection that never had a CONNECT accepted,
    well before the 10 s idle timeout would, and the closed ones are then forgotten."""

    async def check(relay: Relay, result: AttackResult) -> None:
        await until(lambda: relay.quic_connections_serving <= 1 + GOOD_VIEWERS, 4.0)
        # Draining lasts three probe timeouts, which grow with the RTT a loaded host
        # measures (a fresh-clone CI run needed more than 4 s), so that bound is looser.
        await until(lambda: relay.quic_connections <= 1 + GOOD_VIEWERS, 15.0)

    outcome = scenario_test(cert, "garbage_streams", after=check)
    assert_common(outcome)


# -- oversized lengths inside QPACK and moq-lite -----------------------------------------


@pytest.mark.parametrize(
    ("name", "codes"),
    [
        ("qpack_string_length", None),
        ("moq_message_length", {ErrorCode.LIMIT_EXCEEDED, ErrorCode.PROTOCOL_VIOLATION}),
        ("moq_string_length", {ErrorCode.PROTOCOL_VIOLATION, ErrorCode.LIMIT_EXCEEDED}),
        ("moq_frame_size", {ErrorCode.LIMIT_EXCEEDED}),
    ],
)
def test_oversized_inner_length_closes_the_session(
    cert: CertBundle, name: str, codes: set[int] | None
) -> None:
    outcome = scenario_test(cert, name)
    assert_common(outcome)
    result = outcome.result
    assert result.connections > 0 and result.open_at_end == 0
    assert result.closed_at is not None and result.close_delay_s is not None
    assert result.close_delay_s <= CLOSE_WITHIN_S
    if codes is not None:
        assert result.session_closes and set(result.session_closes) <= codes


PROTOCOL_CLOSES = Expectation(
    "upcast_relay_sessions_closed_total", ("protocol_violation", "limit_exceeded")
)


def test_moq_protocol_error_closes_are_counted(cert: CertBundle) -> None:
    outcome = scenario_test(cert, "moq_string_length", expects=(PROTOCOL_CLOSES,))
    outcome.assert_counted(PROTOCOL_CLOSES)


@pytest.mark.slow
def test_protocol_error_closes_are_logged_at_a_bounded_rate(
    cert: CertBundle, caplog: pytest.LogCaptureFixture
) -> None:
    """Forty sessions that each send garbage within a second: at most ten lines a second
    (and a summary) from the relay, not one line each (issue point 3)."""

    async def attack(ctx: AttackContext, duration_s: float) -> AttackResult:
        result = AttackResult("garbage_sessions")
        conns = await asyncio.gather(
            *(send_garbage(ctx, "wt_bidi", b"\x09garbage") for _ in range(40))
        )
        result.connections = len(conns)
        # aioquic reports a peer's CONNECTION_CLOSE after its draining period (3 PTO).
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not all(c.is_closed for c in conns):
            await asyncio.sleep(0.05)
        for conn in conns:
            result.record_close(conn, first=False)
            conn.vanish()
        return result

    holder: list[Outcome] = []

    async def main() -> None:
        holder.append(await under_attack(cert, attack, duration_s=0.0))

    caplog.clear()
    run(main())
    outcome = holder[0]
    assert len(outcome.result.close_codes) == 40, "every garbage session is closed"
    lines = [
        r for r in caplog.records if r.levelno >= logging.WARNING and r.name.startswith("server.")
    ]
    span = max(1.0, lines[-1].created - lines[0].created) if lines else 1.0
    assert len(lines) <= 10 * (span + 1) + 2, [r.getMessage() for r in lines[:20]]


# -- counts: streams and subscriptions -------------------------------------------------


def test_thousands_of_streams_harm_no_one_else(cert: CertBundle) -> None:
    outcome = scenario_test(cert, "many_streams")
    assert_common(outcome)


def test_thousands_of_request_streams_end_by_the_connect_deadline(cert: CertBundle) -> None:
    outcome = scenario_test(cert, "many_request_streams")
    assert_common(outcome)
    assert outcome.result.open_at_end == 0
    outcome.assert_counted(*SCENARIOS["many_request_streams"].expects)


def test_thousands_of_subscriptions_do_not_multiply_the_relay_egress(cert: CertBundle) -> None:
    """One session subscribing the same track thousands of times must not make the relay
    send every frame hundreds of times (its ingress is bounded, its egress must be too)."""
    frames_out = Expectation("upcast_relay_frames_out_total")
    frames_in = Expectation("upcast_relay_frames_in_total")
    refused = SCENARIOS["many_subscriptions"].expects
    outcome = scenario_test(
        cert, "many_subscriptions", expects=(frames_out, frames_in, *refused), settle_s=1.1
    )
    assert_common(outcome)
    fan_out = outcome.moved[frames_out.describe()] / max(1.0, outcome.moved[frames_in.describe()])
    # The good viewers take GOOD_VIEWERS copies, the attacker two (its subscriptions
    # beyond two of a track are refused, and counted), each of which also starts with
    # the cached frames of the current group: at most two more. 62 before the limit.
    assert fan_out <= GOOD_VIEWERS + 4, f"each frame went out {fan_out:.1f} times"
    outcome.assert_counted(*refused)


# -- viewers that never read -----------------------------------------------------------


def test_viewers_that_never_read_are_skipped_and_survive(cert: CertBundle) -> None:
    """Stalled viewers cost the good ones nothing; their groups are skipped (counted);
    when they read again their connection is alive (no RESET_STREAM past their stream
    credit, issue point 2). Groups of 3 frames: well over 128 streams per stall."""
    outcome = scenario_test(
        cert,
        "stalled_viewers",
        duration_s=3.0,
        group_every=3,
        settle_s=1.1,
        expects=(Expectation(SKIPPED),),
    )
    assert_common(outcome)
    result = outcome.result
    assert result.connections == 8
    assert not result.close_codes, f"stalled viewers were closed: {result.close_codes}"
    assert result.open_at_end == 8
    outcome.assert_counted(Expectation(SKIPPED))


# -- churn ------------------------------------------------------------------------------


def test_connect_storm_leaves_nothing_behind(cert: CertBundle) -> None:
    async def drained(relay: Relay, result: AttackResult) -> None:
        # Each storm client sends one CONNECTION_CLOSE and is gone. Under the storm a
        # loopback datagram can be dropped (a full socket buffer: one fresh-clone CI
        # run), and then only the relay's idle timeout frees that link, as for a
        # vanished client: nothing may be left once it has passed.
        await until(lambda: len(relay.links) == 1 + GOOD_VIEWERS, IDLE_TIMEOUT_S + 2.0, step=0.1)

    outcome = scenario_test(cert, "connect_storm", after=drained)
    assert_common(outcome)
    assert outcome.result.connections > 20
    outcome.assert_counted(*SCENARIOS["connect_storm"].expects)


@pytest.mark.slow
def test_vanished_clients_are_dropped_by_the_idle_timeout(cert: CertBundle) -> None:
    async def drained(relay: Relay, result: AttackResult) -> None:
        await until(lambda: len(relay.links) == 1 + GOOD_VIEWERS, 14.0, step=0.1)

    outcome = scenario_test(cert, "vanishing_clients", after=drained)
    assert_common(outcome)
    assert outcome.result.connections > 10


# -- the CONNECT -----------------------------------------------------------------------


# Sixteen connections' deadlines fire in one burst on the loop the attacker and the
# viewers share; a loaded CI run saw the last close reach the attacker 1.01 s after its
# deadline. 3 s still tells the deadline from the 10 s idle timeout, and the counted
# CONNECT_DEADLINE violations say which of the two closed them.
SLOW_CONNECT_CLOSE_WITHIN_S = 3.0


def test_slow_connects_are_closed_by_the_connect_deadline(cert: CertBundle) -> None:
    deadline = TEST_GUARD.connect_deadline_s
    outcome = scenario_test(
        cert, "slow_connect", duration_s=deadline + SLOW_CONNECT_CLOSE_WITHIN_S + 0.5
    )
    assert_common(outcome)
    result = outcome.result
    assert result.open_at_end == 0, f"{result.open_at_end} slow connections still open"
    assert result.closed_at is not None and result.crossed_at is not None
    assert result.closed_at - result.crossed_at <= deadline + SLOW_CONNECT_CLOSE_WITHIN_S
    outcome.assert_counted(*SCENARIOS["slow_connect"].expects)


def test_wrong_connects_are_refused_and_counted(cert: CertBundle) -> None:
    outcome = scenario_test(cert, "wrong_connects", duration_s=1.0)
    assert_common(outcome)
    statuses = outcome.result.statuses
    assert statuses and "200" not in statuses, statuses
    outcome.assert_counted(*SCENARIOS["wrong_connects"].expects)


def test_bad_tokens_are_refused_counted_and_never_logged(
    cert: CertBundle, key: AuthKey, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    outcome = scenario_test(cert, "bad_tokens", key=key, duration_s=1.0)
    assert_common(outcome)
    result = outcome.result
    assert {"401", "403"} <= set(result.statuses)
    assert set(result.session_closes) == {ErrorCode.UNAUTHORIZED}
    outcome.assert_counted(*SCENARIOS["bad_tokens"].expects)
    # No token (a JWT: base64url JSON header and payload) reaches a log line.
    for record in caplog.records:
        message = record.getMessage()
        assert not JWT_SHAPED.search(message), message
