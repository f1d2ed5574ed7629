"""The page's keyboard, pointer and gamepad capture in headless Chromium (loopback page).

What reaches the in-page "game" (window.loopback.inputs, through the real moq-lite
publisher) after real key and mouse events: every game key once the player has focus
(a click on the picture) and only the movement keys without it, Ctrl/Cmd shortcuts
left to the browser, pointer coordinates over the letterboxed picture, and gamepad
states from a stubbed navigator.getGamepads (headless Chromium has no gamepads).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from server.ops.browser_paths import WEB_ROOT as DIST
from tests.chromium import browser_marks, picture_point

pytestmark = browser_marks(DIST / "test" / "loopback.html")

# Before the player loads: gamepads come from window.fakePads, and every keydown's and
# contextmenu's defaultPrevented is recorded by a listener that runs after the player's.
STUBS = """
window.fakePads = [];
Object.defineProperty(Navigator.prototype, 'getGamepads', {
    configurable: true, value: () => window.fakePads,
});
window.seen = [];
addEventListener('DOMContentLoaded', () => {
    for (const type of ['keydown', 'contextmenu'])
        addEventListener(type, (e) => window.seen.push(
            {type, key: e.key, prevented: e.defaultPrevented}));
});
"""


@pytest.fixture
def page(web_root: str, browser: Any) -> Iterator[Any]:
    page = browser.new_page(viewport={"width": 1000, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.add_init_script(STUBS)
    try:
        page.goto(f"{web_root}/test/loopback.html?jwt=loopback&overlay=0")
        page.wait_for_function("() => window.upcast && window.upcast.stats().framesPresented >= 3")
        page.wait_for_function("() => window.upcast.stats().inputSubscribers > 0")
        yield page
        assert errors == []
        assert page.evaluate("() => window.loopback.errors") == []
    finally:
        page.close()


def _inputs(page: Any, kind: str, at_least: int = 0) -> list[dict[str, Any]]:
    if at_least:
        page.wait_for_function(
            "([k, n]) => window.loopback.inputs.filter(m => m.type === k).length >= n",
            arg=[kind, at_least],
        )
    return [m for m in page.evaluate("() => window.loopback.inputs") if m["type"] == kind]


def _keys(page: Any, at_least: int = 0) -> list[list[str]]:
    return [m["down"] for m in _inputs(page, "keys", at_least)]


def _settle(page: Any) -> None:
    # Two animation frames and a round trip: anything sent has arrived. The marker is
    # looked for among the messages after the send, not as the last one: the player's
    # feedback (every 250 ms, issue 21) may arrive after it, and the wait then timed out.
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    sent = page.evaluate(
        "() => { const n = window.loopback.inputs.length;"
        " window.upcast.send({type: 'keyframe'}); return n; }"
    )
    page.wait_for_function(
        "n => window.loopback.inputs.slice(n).some(m => m.type === 'keyframe')", arg=sent
    )


def _outline(page: Any) -> str:
    return page.evaluate(  # type: ignore[no-any-return]
        "() => getComputedStyle(document.getElementById('screen')).outlineStyle"
    )


def _unfocus(page: Any) -> None:
    page.click("#status")
    assert page.evaluate("() => document.activeElement.id") != "screen"


def test_keys_go_to_the_game_only_while_the_player_has_focus(page: Any) -> None:
    _unfocus(page)
    page.keyboard.press("e")  # not a movement key: the page's
    page.keyboard.press("w")  # a movement key: the game's anywhere, as before
    assert _keys(page, 2) == [["w"], []]
    page.click("#screen")
    assert (
        page.evaluate("() => getComputedStyle(document.getElementById('screen')).outlineStyle")
        == "solid"
    )
    page.keyboard.down("e")
    page.keyboard.down("Shift")
    page.keyboard.down("Digit1")  # key "!": sent as "1", released as "1"
    page.keyboard.up("Shift")
    page.keyboard.up("Digit1")
    page.keyboard.press("Escape")  # the game's: focus stays
    page.keyboard.press("Tab")  # the game's: focus stays
    page.keyboard.press("F4")
    page.keyboard.up("e")
    assert _keys(page, 14)[2:] == [
        ["e"],
        ["e", "shift"],
        ["e", "shift", "1"],
        ["e", "1"],
        ["e"],
        ["e", "escape"],
        ["e"],
        ["e", "tab"],
        ["e"],
        ["e", "f4"],
        ["e"],
        [],
    ]
    assert page.evaluate("() => document.activeElement.id") == "screen"
    seen = page.evaluate("() => window.seen.filter(s => s.type === 'keydown')")
    assert [s["prevented"] for s in seen] == [False, True] + [True] * 6
    # A click elsewhere gives the keys back to the page.
    _unfocus(page)
    assert (
        page.evaluate("() => getComputedStyle(document.getElementById('screen')).outlineStyle")
        == "none"
    )
    page.keyboard.press("e")
    _settle(page)
    assert len(_keys(page)) == 14


def test_ctrl_and_meta_shortcuts_stay_the_browsers(page: Any) -> None:
    page.click("#screen")
    page.evaluate("() => { window.seen.length = 0; }")
    page.keyboard.down("Control")
    page.keyboard.press("KeyF")  # find: the browser's, the game still sees the keys
    page.keyboard.up("Control")
    page.keyboard.down("Meta")
    page.keyboard.press("KeyL")  # Cmd+L: the browser's alone
    page.keyboard.up("Meta")
    page.keyboard.press("KeyZ")
    seen = page.evaluate("() => window.seen")
    assert [(s["key"], s["prevented"]) for s in seen] == [
        ("Control", False),
        ("f", False),
        ("Meta", False),
        ("l", False),
        ("z", True),
    ]
    assert _keys(page, 6) == [["control"], ["control", "f"], ["control"], [], ["z"], []]


def _wait_pointer(page: Any, x: float, y: float, buttons: int) -> None:
    """Until the last pointer message is (x, y, buttons), to within a picture pixel."""
    page.wait_for_function(
        """([x, y, b]) => {
            const p = window.loopback.inputs.filter(m => m.type === 'pointer').at(-1);
            return p && Math.abs(p.x - x) < 3e-3 && Math.abs(p.y - y) < 3e-3 && p.buttons === b;
        }""",
        arg=[x, y, buttons],
    )


@pytest.mark.parametrize(("bar", "size"), [("letterbox", (700, 700)), ("pillarbox", (900, 250))])
def test_pointer_is_absolute_over_the_picture_with_its_buttons(
    page: Any, bar: str, size: tuple[int, int]
) -> None:
    page.evaluate(
        """([w, h]) => Object.assign(document.getElementById('screen').style, {
            width: w + 'px', height: h + 'px', maxWidth: 'none', maxHeight: 'none',
            objectFit: 'contain'})""",
        size,
    )
    _unfocus(page)
    page.mouse.move(*picture_point(page, 0.5, 0.5))  # no focus, no button: not the game's
    _settle(page)
    assert _inputs(page, "pointer") == []
    # The first press on the picture is the game's at once (and gives the player focus).
    page.mouse.move(*picture_point(page, 0.25, 0.5))
    page.mouse.down()
    _wait_pointer(page, 0.25, 0.5, 1)
    assert len(_inputs(page, "pointer")) == 1
    page.mouse.move(*picture_point(page, 0.75, 0.1), steps=5)
    _wait_pointer(page, 0.75, 0.1, 1)
    page.mouse.move(*picture_point(page, 1.5, -0.5))  # off the picture while held: clamped
    page.mouse.up()
    _wait_pointer(page, 1, 0, 0)
    assert all(p["buttons"] == 1 for p in _inputs(page, "pointer")[:-1])
    # Focused, a move over a bar is the picture's nearest edge.
    if bar == "letterbox":  # bars above and below
        page.mouse.move(*picture_point(page, 0.3, -0.05))
        _wait_pointer(page, 0.3, 0, 0)
    else:  # bars left and right
        page.mouse.move(*picture_point(page, -0.05, 0.3))
        _wait_pointer(page, 0, 0.3, 0)
    # Right and middle buttons; the context menu stays closed.
    page.mouse.move(*picture_point(page, 0.5, 0.5))
    for button, mask in (("right", 2), ("middle", 4)):
        page.mouse.down(button=button)
        _wait_pointer(page, 0.5, 0.5, mask)
        page.mouse.up(button=button)
        _wait_pointer(page, 0.5, 0.5, 0)
    menus = page.evaluate("() => window.seen.filter(s => s.type === 'contextmenu')")
    assert menus and all(m["prevented"] for m in menus)
    # Moves are coalesced: 20 in one task are one message, the last position.
    before = len(_inputs(page, "pointer"))
    points = [picture_point(page, 0.5, 0.02 * i) for i in range(1, 21)]
    page.evaluate(
        """points => { const c = document.getElementById('screen');
            for (const [x, y] of points) c.dispatchEvent(
                new PointerEvent('pointermove', {bubbles: true, clientX: x, clientY: y}));
        }""",
        points,
    )
    _settle(page)
    moved = _inputs(page, "pointer")[before:]
    assert len(moved) == 1 and moved[0]["y"] == pytest.approx(0.4, abs=3e-3)
    # Without focus, moves are the page's again.
    _unfocus(page)
    page.mouse.move(*picture_point(page, 0.3, 0.3))
    _settle(page)
    assert len(_inputs(page, "pointer")) == before + 1


def test_gamepad_states_are_sent_on_change_once_per_frame(page: Any) -> None:
    page.evaluate(
        """() => {
            window.pad = {index: 0, connected: true, axes: [0, 0, 0, 0],
                buttons: Array.from({length: 17}, () => ({pressed: false, value: 0}))};
            window.fakePads = [window.pad, null, null, null];
            dispatchEvent(new Event('gamepadconnected'));
        }"""
    )
    assert _inputs(page, "gamepad", 1) == [
        {**_inputs(page, "gamepad")[0], "index": 0, "buttons": [], "axes": [0, 0, 0, 0]}
    ]
    # Several changes inside one frame: only the state at the frame goes out.
    page.evaluate(
        """() => {
            pad.buttons[3].pressed = true;
            pad.buttons[3].pressed = false;
            pad.buttons[0].pressed = true;
            pad.buttons[12].pressed = true;
            pad.axes = [-0.734, 0.1, 0.149, 1.0];  // 0.1, 0.149: inside the dead zone
        }"""
    )
    second = _inputs(page, "gamepad", 2)[1]
    assert (second["buttons"], second["axes"]) == ([0, 12], [-0.73, 0, 0, 1])
    _settle(page)
    assert len(_inputs(page, "gamepad")) == 2  # unchanged state: nothing more
    page.evaluate(
        """() => { window.fakePads = [null, null, null, null];
                   dispatchEvent(new Event('gamepaddisconnected')); }"""
    )
    released = _inputs(page, "gamepad", 3)[2]
    assert (released["index"], released["buttons"], released["axes"]) == (0, [], [0, 0, 0, 0])
    _settle(page)
    assert len(_inputs(page, "gamepad")) == 3
