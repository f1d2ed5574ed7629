"""Browser key names (``KeyboardEvent.key``, lower-cased) -> X keysyms.

Printable characters need no table: in X, a Latin-1 character's keysym is its
code point. The named keys are the ones a keyboard has and a game may bind.
"""

from __future__ import annotations

from Xlib import XK

NAMED_KEYS = {
    "arrowup": "Up",
    "arrowdown": "Down",
    "arrowleft": "Left",
    "arrowright": "Right",
    "space": "space",  # the page sends "space" for " "
    "enter": "Return",
    "escape": "Escape",
    "tab": "Tab",
    "backspace": "BackSpace",
    "delete": "Delete",
    "insert": "Insert",
    "home": "Home",
    "end": "End",
    "pageup": "Prior",
    "pagedown": "Next",
    "shift": "Shift_L",
    "control": "Control_L",
    "alt": "Alt_L",
    "altgraph": "Alt_R",
    "meta": "Super_L",
    "capslock": "Caps_Lock",
    "numlock": "Num_Lock",
    "scrolllock": "Scroll_Lock",
    "contextmenu": "Menu",
    "pause": "Pause",
    "printscreen": "Print",
    **{f"f{n}": f"F{n}" for n in range(1, 13)},
}


def keysym_of(name: str) -> int | None:
    """The keysym for a browser key name, or None if it has none we know."""
    if len(name) == 1:
        code = ord(name)
        printable = 0x20 <= code <= 0x7E or 0xA0 <= code <= 0xFF
        return code if printable else None
    x_name = NAMED_KEYS.get(name.lower())
    if x_name is None:
        return None
    keysym = int(XK.string_to_keysym(x_name))
    return keysym or None
