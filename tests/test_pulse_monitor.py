"""PulseMonitor's queue without a server: silence for what has not come, a pile-up
trimmed to MAX_QUEUE_MS from the front, loud samples clipped."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from server.session.pulse_monitor import MAX_QUEUE_MS, SAMPLE_RATE, PulseMonitor


def monitor(tmp_path: Path) -> PulseMonitor:
    m = PulseMonitor(tmp_path / "no-such-socket")  # its recorder waits for the socket
    return m


def test_samples_come_out_in_order_and_missing_ones_are_silence(tmp_path: Path) -> None:
    m = monitor(tmp_path)
    try:
        m._push(np.arange(1, 6, dtype=np.float32) / 10)
        out = m.render(8)
        assert np.allclose(out, [0.1, 0.2, 0.3, 0.4, 0.5, 0, 0, 0])
        assert m.silent == 3
    finally:
        m.close()


def test_a_pile_up_keeps_only_the_newest_samples(tmp_path: Path) -> None:
    m = monitor(tmp_path)
    try:
        limit = SAMPLE_RATE * MAX_QUEUE_MS // 1000
        m._push(np.zeros(limit, np.float32))
        m._push(np.ones(1000, np.float32))
        assert m.dropped == 1000
        out = m.render(limit)
        assert out[-1000:].min() == 1.0 and out[: limit - 1000].max() == 0.0
    finally:
        m.close()


def test_loud_samples_are_clipped(tmp_path: Path) -> None:
    m = monitor(tmp_path)
    try:
        m._push(np.array([2.0, -3.0, 0.5], np.float32))
        assert np.allclose(m.render(3), [1.0, -1.0, 0.5])
    finally:
        m.close()
