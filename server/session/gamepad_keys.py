"""A gamepad's state -> the keyboard keys it holds, for applications that only read keys.

SuperTux, Pingus and most X11 games take the keyboard; few read a joystick, and
none can see the browser's. So a gamepad message (``GamepadMessage``) becomes a
set of held key names, the same names the page's keyboard sends, which the
input router merges with that viewer's keyboard keys.

The default map (``GamepadKeyMap.standard()``) is for the W3C "standard" gamepad
layout (https://w3c.github.io/gamepad/#remapping) and 2D/3D games:

- d-pad 12/13/14/15 and the left stick (axes 0/1 past half way) -> arrow keys:
  arrows move in nearly every keyboard-driven game, and both controls so the
  player uses whichever the game feels right with.
- 0 (A / cross, the bottom face button) -> ``space``: jump / confirm, the most
  used action sits under the thumb.
- 1 (B / circle) -> ``control``: the second action (SuperTux: run/grab, many
  shooters: fire).
- 2 (X / square) -> ``shift`` and 3 (Y / triangle) -> ``alt``: the other
  common modifiers games bind actions to.
- 9 (start) -> ``enter`` and 8 (back / select) -> ``escape``: menus open,
  confirm and close with these in almost every game.

An application with other needs gets its own map from config through
``GamepadKeyMap.parse`` (``{"button:0": "z", "axis:1+": "s"}``); a config model
can also declare a field of type ``GamepadKeyMap`` and pydantic validates it the
same way.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

from pydantic import GetCoreSchemaHandler
from pydantic_core import core_schema

from server.session.viewer_input import (
    MAX_GAMEPAD_AXES,
    MAX_GAMEPAD_BUTTONS,
    PAGE_KEYS,
    GamepadMessage,
)

AXIS_THRESHOLD = 0.5  # a stick past half way holds its key: no drift, no accidental diagonals

Direction = Literal[-1, 1]

_ENTRY = re.compile(r"button:(\d+)|axis:(\d+)([+-])")


def _frozen(mapping: Mapping[Any, str]) -> Mapping[Any, str]:
    return MappingProxyType(dict(mapping))


@dataclass(frozen=True)
class GamepadKeyMap:
    """Button index -> key name, and (axis index, direction) -> key name."""

    buttons: Mapping[int, str] = field(default_factory=dict)
    axes: Mapping[tuple[int, Direction], str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Read-only views: a map shared by many sessions cannot be changed by one.
        object.__setattr__(self, "buttons", _frozen(self.buttons))
        object.__setattr__(self, "axes", _frozen(self.axes))

    @classmethod
    def standard(cls) -> GamepadKeyMap:
        """The default for the W3C standard layout (the module docstring says why)."""
        arrows = {12: "arrowup", 13: "arrowdown", 14: "arrowleft", 15: "arrowright"}
        actions = {0: "space", 1: "control", 2: "shift", 3: "alt", 9: "enter", 8: "escape"}
        stick: dict[tuple[int, Direction], str] = {
            (0, -1): "arrowleft",
            (0, 1): "arrowright",
            (1, -1): "arrowup",  # the Gamepad API's y axis points down
            (1, 1): "arrowdown",
        }
        return cls(buttons={**arrows, **actions}, axes=stick)

    @classmethod
    def parse(cls, spec: Mapping[str, str]) -> GamepadKeyMap:
        """A map from config: ``{"button:0": "space", "axis:0-": "arrowleft", ...}``.

        Raises ValueError naming the first bad entry: an unknown form, an index the
        page never sends, or a key name the page's keyboard does not have.
        """
        buttons: dict[int, str] = {}
        axes: dict[tuple[int, Direction], str] = {}
        for entry, key in spec.items():
            match = _ENTRY.fullmatch(entry) if isinstance(entry, str) else None
            if match is None:
                raise ValueError(
                    f"gamepad map entry {entry!r}: expected 'button:N' or 'axis:N+' / 'axis:N-'"
                )
            if not isinstance(key, str) or key not in PAGE_KEYS:
                raise ValueError(
                    f"gamepad map entry {entry!r}: {key!r} is not a key name the page sends "
                    "(KeyboardEvent.key lower-cased, 'space', 'arrowleft', 'f1', ...)"
                )
            button, axis, sign = match.groups()
            if button is not None:
                if int(button) >= MAX_GAMEPAD_BUTTONS:
                    raise ValueError(
                        f"gamepad map entry {entry!r}: buttons are 0..{MAX_GAMEPAD_BUTTONS - 1}"
                    )
                buttons[int(button)] = key
            else:
                if int(axis) >= MAX_GAMEPAD_AXES:
                    raise ValueError(
                        f"gamepad map entry {entry!r}: axes are 0..{MAX_GAMEPAD_AXES - 1}"
                    )
                axes[(int(axis), 1 if sign == "+" else -1)] = key
        return cls(buttons=buttons, axes=axes)

    def spec(self) -> dict[str, str]:
        """The config form ``parse`` reads (``parse(m.spec()) == m``)."""
        out = {f"button:{b}": key for b, key in sorted(self.buttons.items())}
        for (axis, direction), key in sorted(self.axes.items()):
            out[f"axis:{axis}{'+' if direction > 0 else '-'}"] = key
        return out

    def keys_for(self, message: GamepadMessage) -> frozenset[str]:
        """The keys this gamepad state holds."""
        held = {self.buttons[b] for b in message.buttons if b in self.buttons}
        for (axis, direction), key in self.axes.items():
            if axis < len(message.axes) and message.axes[axis] * direction > AXIS_THRESHOLD:
                held.add(key)
        return frozenset(held)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GamepadKeyMap):
            return NotImplemented
        return dict(self.buttons) == dict(other.buttons) and dict(self.axes) == dict(other.axes)

    def __hash__(self) -> int:
        return hash((frozenset(self.buttons.items()), frozenset(self.axes.items())))

    @classmethod
    def __get_pydantic_core_schema__(
        cls, source: type[Any], handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        # In a pydantic config model the field takes the same spec as ``parse`` (or a
        # ready map); parse's ValueError becomes the ValidationError naming the entry.
        from_spec = core_schema.no_info_after_validator_function(
            cls.parse,
            core_schema.dict_schema(core_schema.str_schema(), core_schema.str_schema()),
        )
        return core_schema.json_or_python_schema(
            json_schema=from_spec,
            python_schema=core_schema.union_schema(
                [core_schema.is_instance_schema(cls), from_spec]
            ),
            serialization=core_schema.plain_serializer_function_ser_schema(
                lambda m: m.spec(), when_used="always"
            ),
        )


DEFAULT_GAMEPAD_KEYS = GamepadKeyMap.standard()
