// Gamepads (W3C Gamepad API) -> {type:"gamepad", index, buttons, axes} messages.
// The API has no events for button presses: it is polled, once per animation frame and
// only while a pad is connected, and a message goes out only when a pad's state changes
// (so at most one per pad per frame). The server maps states to keys
// (server/session/gamepad_keys.py).

export type GamepadState = { index: number; buttons: number[]; axes: number[] };

export const MAX_GAMEPADS = 4; // server/session/viewer_input.py MAX_GAMEPADS
const MAX_BUTTONS = 32;
const MAX_AXES = 8;
const DEADZONE = 0.15; // sticks rest a little off centre; below this they read 0

/** One pad's state as sent: pressed button indices, axes in the dead zone at 0, 2 decimals. */
export function readPad(pad: Gamepad): GamepadState {
	const buttons: number[] = [];
	pad.buttons.slice(0, MAX_BUTTONS).forEach((button, i) => {
		if (button.pressed) buttons.push(i);
	});
	const axes = Array.from(pad.axes.slice(0, MAX_AXES), (v) => {
		if (!Number.isFinite(v) || Math.abs(v) < DEADZONE) return 0;
		return Math.round(Math.max(-1, Math.min(1, v)) * 100) / 100 || 0; // || 0: no -0
	});
	return { index: pad.index, buttons, axes };
}

export class GamepadPoller {
	readonly #send: (state: GamepadState) => void;
	// index -> the state last sent, as JSON (cheap to compare)
	readonly #last = new Map<number, { state: GamepadState; json: string }>();
	#frame = 0;

	constructor(send: (state: GamepadState) => void) {
		this.#send = send;
		window.addEventListener("gamepadconnected", this.#start);
		// The next poll no longer sees the pad and sends its released state.
		window.addEventListener("gamepaddisconnected", this.#start);
		if (pads().length > 0) this.#start(); // connected before the page loaded
	}

	#start = (): void => {
		if (!this.#frame) this.#frame = requestAnimationFrame(this.#poll);
	};

	#poll = (): void => {
		this.#frame = 0;
		const seen = new Set<number>();
		for (const pad of pads()) {
			seen.add(pad.index);
			const state = readPad(pad);
			const json = JSON.stringify(state);
			if (this.#last.get(pad.index)?.json === json) continue;
			this.#last.set(pad.index, { state, json });
			this.#send(state);
		}
		for (const [index, { state }] of this.#last) {
			if (seen.has(index)) continue;
			this.#last.delete(index);
			// Gone mid-press: the game must not keep the buttons held.
			this.#send({ index, buttons: [], axes: state.axes.map(() => 0) });
		}
		if (seen.size > 0) this.#start();
	};
}

function pads(): Gamepad[] {
	const all = typeof navigator.getGamepads === "function" ? navigator.getGamepads() : [];
	return Array.from(all).filter((pad): pad is Gamepad => pad !== null && pad.connected !== false && pad.index >= 0 && pad.index < MAX_GAMEPADS);
}
