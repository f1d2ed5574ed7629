// Viewer input -> the game, as a moq-lite broadcast the page PUBLISHES:
// `<broadcast>/input/<random id>` with one track `input`, one JSON object per frame.
// Why publish instead of a side channel: it crosses any moq-lite relay unchanged; the
// game session announces interest in `<broadcast>/input/` and subscribes each viewer.
import * as Moq from "@moq/lite";
import { wallMs } from "./clock";
import type { FeedbackBody } from "./feedback";
import { PlayerFocus } from "./focus";
import { type GamepadState, GamepadPoller } from "./gamepad";
import { keyName, MOVEMENT_KEYS } from "./keys";
import { type PointerState, PointerCapture } from "./pointer";

export const INPUT_TRACK = "input";

export type InputMessage =
	| { type: "keys"; down: string[] }
	// locked: sent under pointer lock (unbounded relative motion); a captured application
	// takes only those as relative moves, the absolute `pointer` carries drags.
	| { type: "look"; dx: number; dy: number; locked?: boolean }
	| ({ type: "pointer" } & PointerState)
	| ({ type: "gamepad" } & GamepadState)
	| { type: "control"; upscaler?: string; scale?: number; frame_generation?: boolean; cache_policy?: string }
	| { type: "keyframe" }
	// What the page received lately (client_web/src/feedback.ts), every 250 ms.
	| FeedbackBody;

export type SentMessage = InputMessage & { seq: number; sent_ms: number };

export class InputPublisher {
	readonly path: Moq.Path.Valid;
	#seq = 0;
	#broadcast?: Moq.Broadcast;
	// One open group per subscriber track: frames stay in order on one QUIC stream.
	readonly #groups = new Map<Moq.Track, Moq.Group>();
	sent = 0;
	/** Every message as sent, for key-press bookkeeping (input-to-photon). */
	onSend?: (message: SentMessage) => void;

	constructor(broadcast: string) {
		const id = crypto.randomUUID().slice(0, 8);
		this.path = Moq.Path.from(`${broadcast}/input/${id}`);
	}

	/** Publish on a (new) connection; the id stays the same across reconnects. */
	attach(connection: Moq.Connection.Established): void {
		this.detach();
		const broadcast = new Moq.Broadcast();
		this.#broadcast = broadcast;
		connection.publish(this.path, broadcast);
		void this.#serve(broadcast);
		console.info("upcast: publishing input as", this.path);
	}

	detach(): void {
		this.#broadcast?.close();
		this.#broadcast = undefined;
		for (const track of this.#groups.keys()) track.close();
		this.#groups.clear();
	}

	// Answer the relay's subscriptions: only `input` exists.
	async #serve(broadcast: Moq.Broadcast): Promise<void> {
		try {
			for (;;) {
				const request = await broadcast.requested();
				if (!request) return;
				const track = request.track;
				if (track.name !== INPUT_TRACK) {
					track.close(new Error(`no track ${track.name}`));
					continue;
				}
				this.#groups.set(track, track.appendGroup());
				void track.closed.finally(() => this.#groups.delete(track));
				console.info("upcast: input track subscribed");
			}
		} catch (err) {
			console.warn("upcast: input broadcast closed:", err);
		}
	}

	get subscribers(): number {
		return this.#groups.size;
	}

	send(message: InputMessage): SentMessage {
		const sent: SentMessage = { ...message, seq: ++this.#seq, sent_ms: wallMs() };
		const bytes = new TextEncoder().encode(JSON.stringify(sent));
		for (const group of this.#groups.values()) {
			try {
				group.writeFrame(bytes);
			} catch (err) {
				console.warn("upcast: input write failed:", err);
			}
		}
		this.sent++;
		this.onSend?.(sent);
		return sent;
	}
}

const MAX_KEYS = 16; // server/session/viewer_input.py MAX_KEYS: more is refused

/**
 * Keyboard, mouse and gamepads on `target` -> keys / look / pointer / gamepad messages.
 * The movement keys are the page's anywhere (as always); every other game key, and the
 * pointer without a button down on the picture, only while the player has focus (a
 * click on the picture; a click elsewhere gives the page its keys back).
 */
export class InputCapture {
	// KeyboardEvent.code -> the name sent: a key is released by the same physical key even
	// when shift changed its `key` in between ("1" down, shift, "!" up).
	readonly #held = new Map<string, string>();
	readonly #publisher: InputPublisher;
	readonly #target: HTMLElement;
	readonly #focus: PlayerFocus;
	readonly #pointer: PointerCapture;
	#dragging = false;
	// Mouse deltas are summed and flushed once per animation frame: one message per
	// displayed frame is as fine-grained as the game can use.
	#dx = 0;
	#dy = 0;
	#flushScheduled = false;
	/** Key presses (a key added to the held set): seq and sent_ms, for input-to-photon. */
	onPress?: (seq: number, sentMs: number) => void;

	constructor(target: HTMLElement, publisher: InputPublisher) {
		this.#target = target;
		this.#publisher = publisher;
		this.#focus = new PlayerFocus(target);
		this.#pointer = new PointerCapture(target, (state) => publisher.send({ type: "pointer", ...state }), () => this.#focus.focused);
		this.#focus.onBlur = () => {
			this.#releaseAll();
			this.#pointer.release();
		};
		new GamepadPoller((state) => publisher.send({ type: "gamepad", ...state }));
		window.addEventListener("keydown", this.#keydown);
		window.addEventListener("keyup", this.#keyup);
		// Releasing keys while the page is in the background would otherwise be missed.
		window.addEventListener("blur", () => {
			this.#releaseAll();
			this.#pointer.release();
		});
		target.addEventListener("pointerdown", this.#pointerdown);
		window.addEventListener("pointerup", this.#pointerup);
		window.addEventListener("pointermove", this.#pointermove);
	}

	#down(): string[] {
		return [...new Set(this.#held.values())];
	}

	#keydown = (event: KeyboardEvent): void => {
		if (isFormField(event.target)) return;
		// Cmd+key: the browser's and the OS's (macOS never sends the key's keyup).
		if (event.metaKey) return;
		const name = keyName(event);
		if (!name || !(MOVEMENT_KEYS.has(name) || this.#focus.focused)) return;
		// Ctrl+W, Ctrl+R, Ctrl+T... stay the browser's; the game still sees the keys
		// (ctrl+arrow is "run" in SuperTux).
		if (!event.ctrlKey) event.preventDefault(); // arrows and space would scroll, tab move focus
		const id = event.code || name;
		if (this.#held.has(id)) return; // auto-repeat: state unchanged
		const down = this.#down();
		if (!down.includes(name) && down.length >= MAX_KEYS) return;
		this.#held.set(id, name);
		if (down.includes(name)) return; // the other shift: the name was already held
		const sent = this.#publisher.send({ type: "keys", down: this.#down() });
		this.onPress?.(sent.seq, sent.sent_ms);
	};

	#keyup = (event: KeyboardEvent): void => {
		const name = keyName(event);
		const id = event.code || name;
		if (!id || !this.#held.has(id)) return;
		const before = this.#down().length;
		this.#held.delete(id);
		if (this.#down().length !== before) this.#publisher.send({ type: "keys", down: this.#down() });
	};

	#releaseAll = (): void => {
		if (this.#held.size === 0) return;
		this.#held.clear();
		this.#publisher.send({ type: "keys", down: [] });
	};

	#pointerdown = (event: PointerEvent): void => {
		if (event.button !== 0) return;
		this.#dragging = true;
		// Pointer lock (optional) gives unbounded deltas; dragging works without it.
		if (event.shiftKey) void this.#target.requestPointerLock?.();
	};

	#pointerup = (): void => {
		this.#dragging = false;
	};

	#pointermove = (event: PointerEvent): void => {
		if (!this.#dragging && document.pointerLockElement !== this.#target) return;
		this.#dx += event.movementX;
		this.#dy += event.movementY;
		if (!this.#flushScheduled) {
			this.#flushScheduled = true;
			requestAnimationFrame(this.#flushLook);
		}
	};

	#flushLook = (): void => {
		this.#flushScheduled = false;
		if (this.#dx === 0 && this.#dy === 0) return;
		const locked = document.pointerLockElement === this.#target;
		this.#publisher.send({ type: "look", dx: this.#dx, dy: this.#dy, ...(locked ? { locked } : {}) });
		this.#dx = 0;
		this.#dy = 0;
	};
}

function isFormField(target: EventTarget | null): boolean {
	return target instanceof HTMLInputElement || target instanceof HTMLSelectElement || target instanceof HTMLTextAreaElement;
}
