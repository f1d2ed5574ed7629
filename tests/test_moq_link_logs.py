"""A flood of protocol-error closes writes a handful of WARNING lines, not one each."""

from __future__ import annotations

import asyncio
import logging

import pytest

import server.quic.moq_link as moq_link
from server.moq.errors import ErrorCode
from server.quic.moq_link import MoqLink
from server.quic.refusals import RateLimitedLog


class FakeWt:
    """The few WtSession members MoqLink uses; everything sent is dropped."""

    is_client = False
    remote_address = ("203.0.113.7", 4433)

    def __init__(self) -> None:
        self.closes: list[tuple[int, str]] = []
        self._next = 1

    def open_stream(self, is_unidirectional: bool) -> int:
        self._next += 4
        return self._next

    def can_open_stream(self, is_unidirectional: bool) -> bool:
        return True

    def send(self, stream_id: int, data: bytes, end_stream: bool = False) -> None:
        pass

    def reset_stream(self, stream_id: int, code: int) -> None:
        pass

    def stop_sending(self, stream_id: int, code: int) -> None:
        pass

    def close(self, code: int = 0, reason: str = "") -> None:
        self.closes.append((code, reason))


def new_link() -> tuple[MoqLink, FakeWt]:
    wt = FakeWt()
    link = MoqLink(wt)  # type: ignore[arg-type]
    return link, wt


@pytest.fixture
def fresh_limit(monkeypatch: pytest.MonkeyPatch) -> RateLimitedLog:
    """The process-wide limiter as configured, but with this test's count from zero."""
    real = moq_link.warnings_log
    fresh = RateLimitedLog(real.max_lines_per_s, logger=moq_link.log, summary=real.summary)
    monkeypatch.setattr(moq_link, "warnings_log", fresh)
    return fresh


def test_a_thousand_protocol_errors_log_at_most_a_dozen_lines(
    fresh_limit: RateLimitedLog, caplog: pytest.LogCaptureFixture
) -> None:
    async def flood() -> None:
        for _ in range(1000):
            link, wt = new_link()
            # Garbage on a client bidi stream: an unknown stream type closes the session.
            link.on_stream_data(0, b"\xff\xff\xff\xff garbage", False)
            assert wt.closes and wt.closes[0][0] == ErrorCode.PROTOCOL_VIOLATION
        await asyncio.sleep(1.2)  # the summary line comes once the second is over

    with caplog.at_level(logging.DEBUG, logger="server.quic.moq_link"):
        asyncio.run(flood())
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) <= 12, warnings
    assert sum("closed:" in w for w in warnings) == fresh_limit.max_lines_per_s
    assert "990 more moq session warnings (log lines suppressed)" in warnings[-1]
    assert fresh_limit.total == 1000


def test_a_clean_close_stays_info_and_is_not_counted(
    fresh_limit: RateLimitedLog, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger="server.quic.moq_link"):
        for _ in range(50):
            link, _ = new_link()
            link.close(0, "bye")
    levels = {r.levelno for r in caplog.records}
    assert levels == {logging.INFO} and len(caplog.records) == 50
    assert fresh_limit.total == 0


def test_summary_is_rescheduled_on_a_new_event_loop(caplog: pytest.LogCaptureFixture) -> None:
    """The limiter is process-wide and outlives event loops (asyncio.run per test):
    a summary pending on a loop that ended must still be written on the next one."""
    now = [0.0]
    name = "upcast.test.limit"
    limited = RateLimitedLog(1, clock=lambda: now[0], logger=logging.getLogger(name))

    async def burst(n: int, wait_s: float) -> None:
        for _ in range(n):
            limited.warning("line")
        await asyncio.sleep(wait_s)

    with caplog.at_level(logging.WARNING, logger=name):
        asyncio.run(burst(3, 0.0))  # ends before its summary timer fires
        now[0] = 0.5  # the same second, a new loop
        asyncio.run(burst(1, 1.1))
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["line", "3 more warnings (log lines suppressed)"]
