"""``upcast bench adaptive``'s arithmetic: per-second bins, recovery time, the log lines
it counts as switches, and the render size of a fixed setting (server/bench/adaptive/bench.py).
The benchmark itself runs ``upcast serve`` for minutes: it is run by hand, not here."""

from __future__ import annotations

import pytest

from server.bench.adaptive.bench import (
    _back_at,
    _bins,
    _changes,
    _parse_fixed,
    _rate_at,
    _size_for,
    _stepped_up_after,
)
from server.session.quality.figures import load_figures
from server.session.quality.model import QualityModel, Setting


def test_bins_count_arrivals_per_second_inside_the_window() -> None:
    arrivals = [9.5, 10.0, 10.2, 10.9, 11.5, 12.99, 13.0, 14.0]
    assert _bins(arrivals, 10.0, 13.0) == [3.0, 1.0, 1.0]


def test_recovery_needs_two_seconds_in_a_row_at_90_percent() -> None:
    bins = [30.0, 12.0, 28.0, 20.0, 27.0, 29.0, 30.0]
    assert _back_at(bins, 1, 30.0) == 3.0  # bins 4 and 5
    assert _back_at([10.0, 10.0], 0, 30.0) is None


def test_switches_are_the_quality_lines_of_each_session() -> None:
    log = "\n".join(
        [
            "2026 INFO [game-1] server.session.quality.adapter: quality down: a -> b (x; y)",
            "2026 INFO [game-2] server.session.quality.adapter: quality up: b -> c (z)",
            "2026 INFO [game-1] server.session.quality.adapter: quality: auto from a",
            "2026 INFO [game-1] server.session.input_router: render scale 4 requested",
            "2026 WARNING [game-1] server.session.quality.adapter: quality back: c -> b (w)",
        ]
    )
    changes = _changes(log)
    assert changes == {
        "game-1": ["quality down: a -> b (x; y)", "quality back: c -> b (w)"],
        "game-2": ["quality up: b -> c (z)"],
    }


def test_fixed_settings_and_their_render_sizes() -> None:
    assert _parse_fixed("fitted, temporal@2, bilinear@2.667") == [
        None,
        Setting("temporal", 2.0),
        Setting("bilinear", 2.667),
    ]
    assert _size_for("1280x720", 2.0) == "640x360"
    assert _size_for("1280x720", 2.667) == "480x270"
    with pytest.raises(ValueError):
        _parse_fixed("temporal@two")


def test_each_second_is_held_to_the_rate_the_session_ran_at() -> None:
    """A session that lowered its frame rate at 3 s is judged against 15 fps after it."""
    timeline = [(0.2, Setting("bilinear", 4.0)), (3.1, Setting("bilinear", 4.0, rate=0.5))]
    assert _rate_at(timeline, 0.0) == 1.0
    assert _rate_at(timeline, 2.5) == 1.0
    assert _rate_at(timeline, 3.5) == 0.5
    assert _rate_at([], 9.0) == 1.0


def test_the_step_up_after_the_hog_is_a_higher_rate_or_a_better_picture() -> None:
    model = QualityModel(load_figures(), 1280 * 720)
    low = Setting("bilinear", 4.0, rate=2 / 3)
    timeline = [(29.0, low), (30.0, low), (31.0, low), (33.0, Setting("bilinear", 4.0)),
                (36.0, Setting("bilinear", 3.0))]  # fmt: skip
    assert _stepped_up_after(timeline, 30.0, model) == 3.0  # the rate, first
    same_rate = [(30.0, Setting("bilinear", 4.0)), (32.0, Setting("bilinear", 4.0)),
                 (34.5, Setting("bilinear", 3.5))]  # fmt: skip
    assert _stepped_up_after(same_rate, 30.0, model) == 4.5
    assert _stepped_up_after(same_rate[:2], 30.0, model) is None
    assert _stepped_up_after([(31.0, low)], 30.0, model) is None  # nothing before
