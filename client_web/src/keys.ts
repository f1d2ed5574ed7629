// Which keyboard keys go to the game, and under which name (server/session/viewer_input.py
// PAGE_KEYS lists the same names; tests/test_gamepad_keys.py checks they agree).
// Names are KeyboardEvent.key lower-cased, " " as "space": the names the built-in game
// always understood, and what the X11 side turns into keysyms.

/** Captured anywhere on the page (not in form fields): the built-in game's movement keys. */
export const MOVEMENT_KEYS: ReadonlySet<string> = new Set(["w", "a", "s", "d", "arrowup", "arrowdown", "arrowleft", "arrowright", "space", "c"]);

/** Every name the page sends; all but MOVEMENT_KEYS only while the player has focus. */
export const GAME_KEYS: readonly string[] = [
	"a", "b", "c", "d", "e", "f", "g", "h", "i", "j", "k", "l", "m",
	"n", "o", "p", "q", "r", "s", "t", "u", "v", "w", "x", "y", "z",
	"0", "1", "2", "3", "4", "5", "6", "7", "8", "9",
	"-", "=", "[", "]", "\\", ";", "'", ",", ".", "/", "`",
	"arrowup", "arrowdown", "arrowleft", "arrowright",
	"space", "enter", "escape", "tab", "backspace", "shift", "control", "alt",
	"f1", "f2", "f3", "f4", "f5", "f6", "f7", "f8", "f9", "f10", "f11", "f12",
];

const KNOWN: ReadonlySet<string> = new Set(GAME_KEYS);

// KeyboardEvent.code -> the US-layout name, for keys whose `key` is not a game key:
// shift+1 gives key "!" and an AZERTY 1 gives "&"; the game gets "shift" + "1" (which X11
// turns into "!" like a real keyboard would) instead of losing the key.
const CODE_PUNCTUATION: Readonly<Record<string, string>> = {
	Minus: "-",
	Equal: "=",
	BracketLeft: "[",
	BracketRight: "]",
	Backslash: "\\",
	Semicolon: ";",
	Quote: "'",
	Comma: ",",
	Period: ".",
	Slash: "/",
	Backquote: "`",
	NumpadEnter: "enter",
};

/** The game's name for a key event, or undefined when the game does not get this key. */
export function keyName(event: { key: string; code: string }): string | undefined {
	const key = event.key.toLowerCase();
	if (key === " ") return "space";
	if (KNOWN.has(key)) return key;
	const code = event.code;
	if (/^Key[A-Z]$/.test(code)) return code.slice(3).toLowerCase();
	if (/^(Digit|Numpad)[0-9]$/.test(code)) return code.slice(-1);
	return CODE_PUNCTUATION[code];
}
