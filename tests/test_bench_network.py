"""``upcast bench network``: its pieces without a stack (the short real run is in
test_bench_network_e2e.py)."""

from __future__ import annotations

import json

import pytest

from server.bench.network.bench import ladder_divisors, spectator_profiles
from server.bench.network.page import ShownFrames, counter_deltas
from server.bench.network.renditions import RenditionTime
from server.bench.network.series import RateSeries, capacity_bps
from server.bench.network.spectators import Spectator, Spectators, spectator_url, worst
from server.bench.network.table import spectator_table
from server.cli import main
from server.net import PROFILES


def test_capacity_follows_the_schedule() -> None:
    drop = PROFILES["drop"]
    assert [capacity_bps(drop, i) for i in range(3)] == [20e6, 2e6, 20e6]
    blackout = PROFILES["blackout"]
    assert [capacity_bps(blackout, i) for i in range(3)] == [20e6, 0.0, 20e6]
    assert capacity_bps(PROFILES["lan"], 0) is None


def test_rate_series_takes_rates_over_each_span() -> None:
    series = RateSeries(PROFILES["drop"], t0=100.0)
    series.sample(100.0, target_bps=3_000_000, step=0, link_bytes=0, page_bytes=None)
    series.sample(100.5, target_bps=3_000_000, step=0, link_bytes=125_000, page_bytes=1000)
    series.sample(
        101.0, target_bps=1_000_000, step=1, link_bytes=250_000, page_bytes=63_500, frame_divisor=2
    )
    data = series.as_dict()
    assert data["t_s"] == [0.5, 1.0]
    assert data["capacity_bps"] == [20e6, 2e6]
    assert data["link_delivered_bps"] == [2e6, 2e6]
    assert data["page_received_bps"] == [None, 1e6]
    assert data["bitrate_target_bps"] == [3_000_000, 1_000_000]
    assert data["frame_divisor"] == [None, 2]
    assert series.means()["capacity_bps"] == 11e6


def test_freezes_between_drawn_frames() -> None:
    shown = ShownFrames()
    shown.start([0.0, 33.0])  # before the window: only the last draw counts
    shown.add([66.0, 99.0, 400.0, 433.0])  # one gap of 301 ms
    shown.add([466.0])
    shown.finish(1000.0)  # still frozen at the end: 534 ms
    assert shown.shown == 5
    s = shown.summary()
    assert s["count"] == 2
    assert s["total_ms"] == pytest.approx(301 + 534)
    assert s["longest_ms"] == pytest.approx(534)


def test_page_counters_are_differences_of_what_the_page_has() -> None:
    start = {"framesLost": 2, "groupsSkipped": 1, "late": 0, "recovery": {"keyframeRequests": 1}}
    end: dict[str, object] = {"framesLost": 5, "groupsSkipped": 1, "late": 4}
    end |= {"longestFreezeMs": 250.0, "recovery": {"keyframeRequests": 3}}
    deltas = counter_deltas(start, end)
    assert deltas == {
        "framesLost": 3,
        "groupsSkipped": 0,
        "late": 4,
        "longestFreezeMs_since_start": 250.0,
        "recovery_keyframeRequests": 2,
    }
    assert counter_deltas({}, {}) == {}


def test_bad_arguments_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "network", "--profile", "moon"]) == 2
    assert "unknown profile 'moon'" in capsys.readouterr().err
    assert main(["bench", "network", "--seconds", "0"]) == 2


def test_spectator_profiles_are_a_repeatable_comma_list() -> None:
    assert spectator_profiles(None) == []
    assert spectator_profiles(["lan,lte", " wifi ", "lte"]) == ["lan", "lte", "wifi", "lte"]


def test_bad_spectators_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "network", "--profile", "lan", "--spectators", "lan,moon"]) == 2
    err = capsys.readouterr().err
    assert "--spectators: unknown profile 'moon'" in err and "lte" in err  # names the choices
    assert main(["bench", "network", "--spectators", ","]) == 2
    assert "name at least one profile" in capsys.readouterr().err
    assert main(["bench", "network", "--spectators", ",".join(["lan"] * 9)]) == 2
    assert "at most 8" in capsys.readouterr().err
    assert main(["bench", "network", "--spectators", "lte", "--ladder", "1,2"]) == 2
    assert "--ladder: ladder divisors must be at least 2" in capsys.readouterr().err


def test_the_ladder_is_on_for_spectators_only_unless_asked() -> None:
    assert ladder_divisors(None, []) == ()  # the player alone, as before --spectators
    assert ladder_divisors(None, ["lte"]) == (2, 4)  # as upcast up
    assert ladder_divisors("off", ["lte"]) == ()
    assert ladder_divisors("4", []) == (4,)


def test_spectators_are_named_by_profile_and_count_repeats() -> None:
    group = Spectators(["lan", "lte", "lan"])
    assert [m.name for m in group.members] == ["lan#1", "lte", "lan#2"]
    assert [m.seed for m in group.members] == [1, 2, 3]  # the player's link has seed 0
    assert spectator_url(4443, "game", 4450) == (
        "http://localhost:4443/?broadcast=game&overlay=0&port=4450"
    )


def test_rendition_figures_are_the_pages_own() -> None:
    clock = RenditionTime()
    stats = {"rendition": "video.640x360", "renditionSwitches": 2, "abr": {"mode": "abr"}}
    clock.update(stats | {"renditionSeconds": {"video.320x180": 1.5, "video.640x360": 3.25}})
    clock.update({"renditionSwitches": 2, "renditionSeconds": {"video.640x360": 3.5}})
    s = clock.summary()  # between subscriptions (no rendition): the last one stands
    assert s["rendition"] == "video.640x360"
    assert (s["rendition_seconds"], s["rendition_switches"]) == ({"video.640x360": 3.5}, 2)


def test_rendition_figures_are_null_when_the_page_says_nothing() -> None:
    clock = RenditionTime()
    clock.update({"framesPresented": 10})
    assert clock.summary() == {
        "rendition": None,
        "rendition_seconds": None,
        "rendition_switches": None,
        "abr": None,
    }


def _spectator(
    name: str, first: float | None, ratio: float | None, longest: float
) -> dict[str, object]:
    return {
        "name": name,
        "first_picture_ms": first,
        "delivered_ratio": ratio,
        "page_fps": None,
        "freezes": {"count": 1 if longest else 0, "longest_ms": longest},
        "median_ms": None,
        "p95_ms": None,
        "rendition_seconds": None,
        "rendition_switches": None,
    }


def test_worst_spectator_figures_across_profiles() -> None:
    cases = [
        {"name": "lan", "spectators": [_spectator("lte", 900.0, 0.8, 400.0)]},
        {"name": "wifi", "spectators": [_spectator("lan", 300.0, 0.95, 0.0)]},
        {"name": "cable", "spectators": [_spectator("drop", None, None, 0.0)]},
        {"name": "lte"},  # a case without spectators
    ]
    worst_of = worst(cases)
    assert worst_of["count"] == 3
    assert worst_of["worst_first_picture_ms"] == {
        "value": 900.0,
        "spectator": "lte",
        "player_profile": "lan",
    }
    assert worst_of["worst_delivered_ratio"]["value"] == 0.8
    assert worst_of["worst_longest_freeze_ms"]["value"] == 400.0
    assert worst_of["without_picture"] == [{"spectator": "drop", "player_profile": "cable"}]
    text = spectator_table(cases)
    assert len(text.splitlines()) == 4 and "900" in text


class _ScriptedPage:
    """What a spectator page answers, read by read: its draws and its stats()."""

    def __init__(self, reads: list[tuple[list[float], dict[str, object] | None]]) -> None:
        self.reads = reads
        self.draws: list[float] = []

    def evaluate(self, script: str) -> object:
        if "__benchDraws" in script:
            if not self.draws and self.reads:
                self.draws, stats = self.reads[0][0], self.reads[0][1]
                self._stats = stats
                self.reads.pop(0)
            draws, self.draws = self.draws, []
            return {"draws": draws, "now": (draws or [0.0])[-1] + 10.0}
        return None if self._stats is None else json.dumps(self._stats)


def test_spectator_counts_published_frames_of_the_track_it_plays() -> None:
    member = Spectator("lte", seed=1, name="lte")
    switched = {"renditionSwitches": 1, "renditionSeconds": {"video.640x360": 0.7}}
    member.joined_at = 0.0
    member._page = _ScriptedPage(
        [
            ([], None),  # loading: no picture yet, no window.upcast
            ([700.0, 733.0], {"framesPresented": 2, "rendition": "video.640x360"}),  # base
            ([766.0, 1400.0], {"framesPresented": 30, "rendition": "video.640x360"}),
            ([1433.0], {"framesPresented": 58, "rendition": "video.320x180"} | switched),
            ([1466.0], {"framesPresented": 86, "rendition": "video.320x180"} | switched),
        ]
    )

    def published(player: int, rung: int) -> dict[str, int]:
        # A thinned player's track (every other frame); the rungs get every frame.
        return {"": player, "video": player, "video.640x360": rung, "video.320x180": rung}

    for at, counts in enumerate([(0, 0), (10, 20), (25, 50), (40, 80)]):
        member.read(float(at), published(*counts))
    member.finish(published(55, 110))
    s = member.summary()
    assert s["first_picture_ms"] == 700.0
    assert s["frames_shown"] == 84  # 86 - 2 at the base read
    assert s["frames_published"] == 90  # rung frames, 20 -> 110
    assert s["frames_published_by_track"] == {"video.640x360": 30, "video.320x180": 60}
    assert s["delivered_ratio"] == round(84 / 90, 4)
    assert s["rendition_switches"] == 1
    assert s["freezes"]["count"] == 1 and s["freezes"]["longest_ms"] == 634.0
