"""How the benchmarks read the page's stats: one JSON string, and only the samples added
since the last read (server/bench/page_stats.py, server/bench/latency.py)."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.bench.latency import StageCollector, new_samples
from server.bench.page_stats import read_latency, read_stats


class _Page:
    def __init__(self, value: Any) -> None:
        self.value = value
        self.scripts: list[str] = []

    def evaluate(self, script: str) -> Any:
        self.scripts.append(script)
        return self.value


def test_stats_travel_as_one_json_string() -> None:
    total = {"p50": 40.5, "n": 2, "samples": [40.5, 41]}
    stats = {"framesPresented": 3, "latency": {"total": total}}
    page = _Page(json.dumps(stats))
    assert read_stats(page) == stats
    assert read_latency(_Page(json.dumps(stats["latency"]))) == stats["latency"]
    assert all("JSON.stringify" in s for s in page.scripts)


@pytest.mark.parametrize("value", [None, "[1, 2]", {"already": "an object"}])
def test_anything_but_an_object_is_an_error_that_says_so(value: Any) -> None:
    with pytest.raises(RuntimeError, match="not an object"):
        read_stats(_Page(value))


# Sample values drawn from few distinct numbers, so repeats (of the last one too) are common.
_values = st.lists(st.sampled_from([10.0, 10.5, 11.0, 12.25]), max_size=40)


@given(old=_values, added=_values, capacity=st.integers(min_value=1, max_value=50))
def test_new_samples_are_exactly_those_pushed_since_the_last_read(
    old: list[float], added: list[float], capacity: int
) -> None:
    """The page's window keeps the last ``capacity`` samples; a read after ``added``
    were pushed gives back ``added`` (the part still in the window) whenever the two
    windows overlap by at least one sample, as they do at the benchmarks' read rates."""
    before = old[-capacity:]
    after = (before + added)[-capacity:]
    if not before or len(added) >= capacity:
        return  # no overlap left: nothing to tell new from old
    got = new_samples(before, after)
    # With repeated values an overlap can look longer than it is; the read then misses
    # samples, never invents them: what comes back is a tail of what was added.
    assert got == added[len(added) - len(got) :] if got else True
    if before[-1] not in added and len(set(before)) == len(before):
        assert got == added


def test_a_collector_keeps_each_sample_once_across_overlapping_reads() -> None:
    collector = StageCollector.empty()
    window: list[float] = []
    pushed: list[float] = []
    for i in range(100):
        value = 30.0 + (i * 7919 % 97) / 8.0
        pushed.append(value)
        window = [*window, value][-20:]
        if i % 7 == 6:
            collector.update({"total": {"samples": list(window)}})
    collector.update({"total": {"samples": list(window)}})
    assert collector.samples["total"] == pushed
