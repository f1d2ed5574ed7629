"""Gamepad state -> held keys: the standard map, per-application maps from config."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

from server.session.gamepad_keys import DEFAULT_GAMEPAD_KEYS, GamepadKeyMap
from server.session.viewer_input import MAX_KEYS, PAGE_KEYS, GamepadMessage

REPO = Path(__file__).resolve().parents[1]


def pad(
    buttons: tuple[int, ...] | list[int] = (), axes: tuple[float, ...] | list[float] = ()
) -> GamepadMessage:
    return GamepadMessage(type="gamepad", index=0, buttons=list(buttons), axes=list(axes))


def test_standard_map_dpad_stick_and_face_buttons() -> None:
    keys = DEFAULT_GAMEPAD_KEYS.keys_for
    assert keys(pad()) == frozenset()
    assert keys(pad([12])) == {"arrowup"}
    assert keys(pad([13, 14])) == {"arrowdown", "arrowleft"}
    assert keys(pad([15])) == {"arrowright"}
    assert keys(pad([0, 1, 2, 3])) == {"space", "control", "shift", "alt"}
    assert keys(pad([9])) == {"enter"} and keys(pad([8])) == {"escape"}
    # Left stick past half way; the y axis points down (W3C).
    assert keys(pad(axes=[-0.8, 0, 0, 0])) == {"arrowleft"}
    assert keys(pad(axes=[0.51, 0.9, 0, 0])) == {"arrowright", "arrowdown"}
    assert keys(pad(axes=[0, -1])) == {"arrowup"}
    # Not past half way, the right stick (axes 2/3), unmapped buttons: nothing.
    assert keys(pad([4, 5, 16, 31], [0.5, -0.5, 1, -1])) == frozenset()
    # The d-pad and the stick on one arrow hold it once.
    assert keys(pad([14], [-1, 0])) == {"arrowleft"}


@given(
    buttons=st.lists(st.integers(0, 31), max_size=32),
    axes=st.lists(st.floats(-1, 1), max_size=8),
)
def test_keys_are_page_key_names_and_never_more_than_the_keyboard_may_hold(
    buttons: list[int], axes: list[float]
) -> None:
    held = DEFAULT_GAMEPAD_KEYS.keys_for(pad(buttons, axes))
    assert held <= PAGE_KEYS and len(held) <= MAX_KEYS


def test_parse_reads_the_config_form_and_round_trips() -> None:
    spec = {"button:0": "z", "button:1": "x", "axis:1+": "s", "axis:1-": "w", "axis:0-": "a"}
    m = GamepadKeyMap.parse(spec)
    assert m.buttons == {0: "z", 1: "x"}
    assert m.axes == {(1, 1): "s", (1, -1): "w", (0, -1): "a"}
    assert m.keys_for(pad([1], [-0.6, 0.7])) == {"x", "a", "s"}
    assert GamepadKeyMap.parse(m.spec()) == m
    assert GamepadKeyMap.parse(DEFAULT_GAMEPAD_KEYS.spec()) == DEFAULT_GAMEPAD_KEYS
    assert GamepadKeyMap.parse({}).keys_for(pad([0], [1])) == frozenset()


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ({"button0": "z"}, "'button0': expected 'button:N'"),
        ({"axis:1": "s"}, "'axis:1': expected"),
        ({"axis:-1+": "s"}, "'axis:-1+': expected"),
        ({"button:0": "z", "button:1": "Z"}, "'button:1': 'Z' is not a key name"),
        ({"button:0": "arowleft"}, "'button:0': 'arowleft' is not a key name"),
        ({"button:32": "z"}, "'button:32': buttons are 0..31"),
        ({"axis:8+": "z"}, "'axis:8+': axes are 0..7"),
    ],
)
def test_parse_errors_name_the_bad_entry(spec: dict[str, str], says: str) -> None:
    with pytest.raises(ValueError, match=re.escape(says)):
        GamepadKeyMap.parse(spec)


def test_a_map_cannot_be_changed_after_it_is_built() -> None:
    m = GamepadKeyMap.parse({"button:0": "z"})
    with pytest.raises(TypeError):
        m.buttons[1] = "x"  # type: ignore[index]
    with pytest.raises(AttributeError):
        m.buttons = {}  # type: ignore[misc]
    assert DEFAULT_GAMEPAD_KEYS.keys_for(pad([0])) == {"space"}
    assert hash(m) == hash(GamepadKeyMap.parse({"button:0": "z"}))


class AppConfig(BaseModel):
    gamepad: GamepadKeyMap = DEFAULT_GAMEPAD_KEYS


def test_a_config_model_validates_the_map_from_json() -> None:
    config = AppConfig.model_validate_json('{"gamepad": {"button:0": "z", "axis:0-": "a"}}')
    assert config.gamepad == GamepadKeyMap(buttons={0: "z"}, axes={(0, -1): "a"})
    assert AppConfig().gamepad is DEFAULT_GAMEPAD_KEYS
    assert (
        AppConfig.model_validate({"gamepad": DEFAULT_GAMEPAD_KEYS}).gamepad is DEFAULT_GAMEPAD_KEYS
    )
    assert AppConfig.model_validate_json(config.model_dump_json()) == config
    with pytest.raises(ValidationError, match=re.escape("'button:x'")):
        AppConfig.model_validate_json('{"gamepad": {"button:x": "z"}}')
    with pytest.raises(ValidationError):
        AppConfig.model_validate_json('{"gamepad": {"button:0": 5}}')


def test_page_keys_match_the_names_the_page_sends() -> None:
    # client_web/src/keys.ts lists the same names: a name only the page has could never
    # be mapped from a gamepad, and a name only the server has is a typo.
    source = (REPO / "client_web" / "src" / "keys.ts").read_text()
    block = source.split("GAME_KEYS: readonly string[] = [")[1].split("];")[0]
    names = [json.loads(s) for s in re.findall(r'"(?:[^"\\]|\\.)*"', block)]
    assert len(names) == len(set(names))
    assert set(names) == PAGE_KEYS
