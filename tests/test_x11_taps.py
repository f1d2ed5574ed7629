"""A tap shorter than a program's frame still reaches a captured application
(X11Source keeps it down for MIN_TAP_S)."""

from __future__ import annotations

from server.game.x11.source import HeldUntilSeen, _bits

HOLD = 0.08


def test_a_quick_tap_stays_down_for_the_minimum_hold() -> None:
    keys: HeldUntilSeen[str] = HeldUntilSeen(HOLD)
    keys.want(frozenset({"enter"}), now=0.0)
    keys.want(frozenset(), now=0.001)  # released in the same tick
    assert keys.down == {"enter"}
    assert not keys.next_tick(now=0.033) and keys.down == {"enter"}
    assert keys.next_tick(now=0.09) and keys.down == frozenset()
    assert not keys.next_tick(now=0.2)


def test_a_key_held_longer_is_released_at_once() -> None:
    keys: HeldUntilSeen[str] = HeldUntilSeen(HOLD)
    keys.want(frozenset({"arrowright"}), now=0.0)
    keys.next_tick(now=0.5)
    keys.want(frozenset(), now=0.5)
    assert keys.down == frozenset()


def test_other_keys_follow_the_viewer_while_a_tap_is_held() -> None:
    keys: HeldUntilSeen[str] = HeldUntilSeen(HOLD)
    keys.want(frozenset({"a"}), now=0.0)
    keys.next_tick(now=0.1)
    keys.want(frozenset({"a", "x"}), now=0.2)
    keys.want(frozenset({"b"}), now=0.21)  # a released (held long), x tapped, b pressed
    assert keys.down == {"x", "b"}
    keys.next_tick(now=0.3)
    assert keys.down == {"b"}


def test_button_masks_split_into_bits() -> None:
    assert _bits(0) == frozenset() and _bits(5) == {1, 4} and sum(_bits(7)) == 7
