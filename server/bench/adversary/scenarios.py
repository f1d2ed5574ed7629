"""The attack scenarios by name, with what the relay must do about each.

Shared by tests/test_relay_adversarial.py and ``upcast bench adversary``. Every scenario
attacks one relay on this machine for a given duration; its loops are bounded in
connections and bytes (adversary_types) as well as in time.
"""

from __future__ import annotations

from server.bench.adversary import connects, h3, sessions
from server.bench.adversary.attack_types import GUARD, SKIPPED, UNAUTHORIZED, Expectation, Scenario


def _guard(*reasons: str) -> tuple[Expectation, ...]:
    return (Expectation(GUARD, reasons),)


_LIST = [
    Scenario(
        "headers_flood",
        h3.headers_flood,
        "request stream: HEADERS claiming 2^62-1 bytes, then bytes forever",
        _guard("h3_frame_too_large"),
    ),
    Scenario(
        "unknown_frame_flood",
        h3.unknown_frame_flood,
        "request stream: a reserved frame type claiming 2^62-1 bytes, then bytes forever",
        _guard("h3_pre_connect_bytes", "h3_overhead_rate"),
    ),
    Scenario(
        "settings_flood",
        h3.settings_flood,
        "own control stream: SETTINGS claiming 2^62-1 bytes, then bytes forever",
        _guard("h3_frame_too_large"),
    ),
    Scenario(
        "control_unknown_flood",
        h3.control_unknown_flood,
        "control stream after SETTINGS: a reserved frame claiming 2^62-1 bytes, forever",
        _guard("h3_stream_buffer", "h3_overhead_rate", "h3_frame_too_large"),
    ),
    Scenario(
        "unknown_uni_flood",
        h3.unknown_uni_flood,
        "a unidirectional stream of a reserved type, fed forever",
        _guard("h3_overhead_rate", "h3_stream_buffer"),
    ),
    Scenario(
        "qpack_encoder_flood",
        h3.qpack_encoder_flood,
        "QPACK encoder stream: valid, useless instructions forever",
        _guard("h3_overhead_rate", "h3_stream_buffer"),
    ),
    Scenario(
        "garbage_streams",
        h3.garbage_streams,
        "random bytes on every stream kind (request, control, unknown uni, QPACK, WT uni/bidi)",
        closes_attacker=False,  # garbage on an ignored stream closes nothing by itself
    ),
    Scenario(
        "qpack_string_length",
        h3.qpack_string_length,
        "HEADERS whose QPACK string length claims 2^62 bytes",
    ),
    Scenario(
        "moq_message_length",
        sessions.moq_message_length,
        "moq-lite SUBSCRIBE whose message length claims 2^62-1 bytes",
    ),
    Scenario(
        "moq_string_length",
        sessions.moq_string_length,
        "moq-lite ANNOUNCE_INTEREST whose prefix string length claims 2^62-1 bytes",
    ),
    Scenario(
        "moq_frame_size",
        sessions.moq_frame_size,
        "an attacker publisher's group frame claiming 2^62-1 bytes",
    ),
    Scenario(
        "many_streams",
        sessions.many_streams,
        "3000 WebTransport streams left open (probes and unfinished group headers)",
    ),
    Scenario(
        "many_subscriptions",
        sessions.many_subscriptions,
        "3000 subscriptions in one session",
        (Expectation("upcast_relay_subscribes_refused_total"),),
    ),
    Scenario(
        "many_request_streams",
        sessions.many_request_streams,
        "5000 HTTP/3 request streams with unfinished HEADERS, no CONNECT ever",
        _guard("h3_streams", "connect_deadline", "h3_pre_connect_bytes", "h3_overhead_rate"),
    ),
    Scenario(
        "stalled_viewers",
        sessions.stalled_viewers,
        "8 viewers that subscribe then never read (no ACKs, no credit), then read again",
        (Expectation(SKIPPED),),
        closes_attacker=False,  # they must survive: skipped, not killed
    ),
    Scenario(
        "connect_storm",
        sessions.connect_storm,
        "connect, CONNECT, subscribe, close; 4 loops as fast as they go",
        _guard("source_connection_rate"),
        closes_attacker=False,
    ),
    Scenario(
        "vanishing_clients",
        sessions.vanishing_clients,
        "sessions that subscribe and vanish without CONNECTION_CLOSE, ~20 a second",
        _guard("source_connections", "source_connection_rate", "unauthenticated_connections"),
        closes_attacker=False,
    ),
    Scenario(
        "slow_connect",
        connects.slow_connect,
        "16 connections that never finish a CONNECT (half send a partial HEADERS)",
        _guard("connect_deadline"),
    ),
    Scenario(
        "wrong_connects",
        connects.wrong_connects,
        "GET, CONNECT without :protocol, :path without /, /../.., %00, 8 KiB (open relay)",
        _guard("bad_path"),
        closes_attacker=False,
    ),
    Scenario(
        "bad_tokens",
        connects.bad_token_attempts,
        "expired, wrong key, alg none, wrong path; a watch-only token that publishes",
        (
            Expectation(UNAUTHORIZED, ("expired_token",)),
            Expectation(UNAUTHORIZED, ("invalid_token",)),
            Expectation(UNAUTHORIZED, ("forbidden_path",)),
            Expectation(UNAUTHORIZED, ("publish_denied",)),
        ),
        auth=True,
    ),
]

SCENARIOS: dict[str, Scenario] = {s.name: s for s in _LIST}
