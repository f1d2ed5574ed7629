"""Link profiles: validation, the issue's named links, schedule files and their errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from server.net.link_profile import Direction, GilbertElliott, LinkProfile, Schedule
from server.net.profiles import PROFILES, ProfileError, load_schedule, resolve


def test_the_named_profiles_are_the_issues() -> None:
    assert set(PROFILES) == {"lan", "cable", "wifi", "lte", "drop", "blackout"}
    lan = PROFILES["lan"].steps[0].profile
    assert lan.down == lan.up == Direction()
    cable = PROFILES["cable"].steps[0].profile
    assert (cable.down.rate_bps, cable.up.rate_bps) == (20e6, None)
    assert cable.down.delay_ms + cable.up.delay_ms == 15.0
    wifi = PROFILES["wifi"].steps[0].profile
    assert (wifi.down.rate_bps, wifi.down.delay_ms * 2, wifi.down.loss) == (8e6, 30.0, 0.01)
    assert wifi.down.jitter_ms + wifi.up.jitter_ms == 10.0
    lte = PROFILES["lte"].steps[0].profile
    assert lte.down.rate_bps == 4e6 and lte.down.delay_ms * 2 == 60.0
    assert lte.down.burst_loss is not None
    assert lte.down.burst_loss.mean_loss == pytest.approx(0.02)
    assert 1.0 / lte.down.burst_loss.p_bad_to_good == pytest.approx(3.0)
    drop = PROFILES["drop"]
    assert [(s.at_s, s.profile.down.rate_bps) for s in drop.steps] == [
        (0.0, 20e6),
        (10.0, 2e6),
        (20.0, 20e6),
    ]
    blackout = PROFILES["blackout"]
    assert [(s.at_s, s.profile.down.loss, s.profile.up.loss) for s in blackout.steps] == [
        (0.0, 0.0, 0.0),
        (5.0, 1.0, 1.0),
        (8.0, 0.0, 0.0),
    ]


def test_one_set_applies_both_ways_and_the_rate_downlink_only() -> None:
    profile = LinkProfile.model_validate({"rate_bps": "20mbit", "delay_ms": 5, "loss": 0.1})
    assert profile.down == Direction(rate_bps=20e6, delay_ms=5, loss=0.1)
    assert profile.up == Direction(delay_ms=5, loss=0.1)
    both = LinkProfile.model_validate({"rate_bps": 8e6, "up_rate_bps": "1 Mbit/s"})
    assert both.up.rate_bps == 1e6
    split = LinkProfile.model_validate({"down": {"delay_ms": 10}, "up": {"delay_ms": 30}})
    assert (split.down.delay_ms, split.up.delay_ms) == (10, 30)


@pytest.mark.parametrize(
    ("text", "bps"),
    [("512kbit", 512e3), ("20mbit", 20e6), ("1.5 Gbit/s", 1.5e9), ("64000", 64e3), ("8Mbps", 8e6)],
)
def test_rates_with_units(text: str, bps: float) -> None:
    assert Direction(rate_bps=text).rate_bps == bps  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"rate_bps": "fast"}, "is not bit/s"),
        ({"rate_bps": 0}, "greater than 0"),
        ({"loss": 1.5}, "less than or equal to 1"),
        ({"delay_ms": -1}, "greater than or equal to 0"),
        ({"ratebps": 1}, "unknown field(s) ratebps"),
        ({"down": {"rate_bps": 1}, "delay_ms": 5}, "delay_ms"),
    ],
)
def test_bad_fields_are_named(fields: dict[str, object], message: str) -> None:
    with pytest.raises(ValidationError, match=message.replace("(", r"\(").replace(")", r"\)")):
        LinkProfile.model_validate(fields)


def test_gilbert_elliott_from_mean() -> None:
    chain = GilbertElliott.from_mean(0.05, 4.0)
    assert chain.p_bad_to_good == 0.25
    assert chain.mean_loss == pytest.approx(0.05)
    with pytest.raises(ValueError, match="burst_length"):
        GilbertElliott.from_mean(0.05, 0.5)
    with pytest.raises(ValueError, match="loss_rate"):
        GilbertElliott.from_mean(1.0, 2.0)


def test_steps_must_start_at_zero_and_increase() -> None:
    cable = PROFILES["cable"].steps[0].profile
    with pytest.raises(ValidationError, match="first step must start at at_s = 0"):
        Schedule.of([(1.0, cable)])
    with pytest.raises(ValidationError, match="increasing at_s"):
        Schedule.of([(0.0, cable), (5.0, cable), (5.0, cable)])
    schedule = Schedule.of([(0.0, cable), (5.0, LinkProfile())])
    assert [schedule.index_at(t) for t in (-1.0, 0.0, 4.99, 5.0, 1e9)] == [0, 0, 0, 1, 1]


def test_a_toml_schedule_file(tmp_path: Path) -> None:
    path = tmp_path / "dip.toml"
    path.write_text(
        'description = "a dip"\n'
        '[[steps]]\nat_s = 0\nrate_bps = "10mbit"\ndelay_ms = 10\n'
        '[[steps]]\nat_s = 5\nrate_bps = "1mbit"\ndelay_ms = 10\n'
        "[steps.burst_loss]\np_good_to_bad = 0.01\np_bad_to_good = 0.5\n"
    )
    schedule = resolve(str(path))
    assert schedule.description == "a dip"
    assert [s.profile.down.rate_bps for s in schedule.steps] == [10e6, 1e6]
    assert schedule.steps[1].profile.up.burst_loss == GilbertElliott(
        p_good_to_bad=0.01, p_bad_to_good=0.5
    )


def test_a_json_file_with_one_profile(tmp_path: Path) -> None:
    path = tmp_path / "wifi.json"
    path.write_text('{"rate_bps": "8mbit", "delay_ms": 15, "jitter_ms": 5, "loss": 0.01}')
    schedule = load_schedule(path)
    assert len(schedule.steps) == 1
    assert schedule.steps[0].profile == PROFILES["wifi"].steps[0].profile


def test_file_errors_say_where(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"steps": [{"at_s": 0, "delay_ms": -3}]}')
    with pytest.raises(ProfileError, match=r"steps\.0\.profile\.down\.delay_ms"):
        resolve(str(bad))
    broken = tmp_path / "broken.toml"
    broken.write_text("at_s = = 0")
    with pytest.raises(ProfileError, match="not valid TOML"):
        resolve(str(broken))
    with pytest.raises(ProfileError, match="cannot read"):
        resolve(str(tmp_path / "missing.json"))
    with pytest.raises(ProfileError, match="unknown profile 'dsl': use one of lan, cable"):
        resolve("dsl")
