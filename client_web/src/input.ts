// Viewer input -> the game, as a moq-lite broadcast the page PUBLISHES:
// `<broadcast>/input/<random id>` with one track `input`, one JSON object per frame.
// Why publish instead of a side channel: it crosses any moq-lite relay unchanged; the
// game session announces interest in `<broadcast>/input/` and subscribes each viewer.
import * as Moq from "@moq/lite";
import { wallMs } from "./clock";

export const INPUT_TRACK = "input";

export type InputMessage =
	| { type: "keys"; down: string[] }
	| { type: "look"; dx: number; dy: number }
	| { type: "control"; upscaler?: string; scale?: number; frame_generation?: boolean; cache_policy?: string }
	| { type: "keyframe" };

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

// KeyboardEvent.key (lower-cased) -> name the game understands (server/session/viewer_input.py).
const KEY_NAMES: Record<string, string> = {
	w: "w",
	a: "a",
	s: "s",
	d: "d",
	arrowup: "arrowup",
	arrowdown: "arrowdown",
	arrowleft: "arrowleft",
	arrowright: "arrowright",
	" ": "space",
	c: "c",
};

/** Keyboard and mouse on `target` -> keys/look messages. */
export class InputCapture {
	readonly #held = new Set<string>();
	readonly #publisher: InputPublisher;
	readonly #target: HTMLElement;
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
		window.addEventListener("keydown", this.#keydown);
		window.addEventListener("keyup", this.#keyup);
		// Releasing keys while the page is in the background would otherwise be missed.
		window.addEventListener("blur", this.#releaseAll);
		target.addEventListener("pointerdown", this.#pointerdown);
		window.addEventListener("pointerup", this.#pointerup);
		window.addEventListener("pointermove", this.#pointermove);
	}

	#keydown = (event: KeyboardEvent): void => {
		if (isFormField(event.target)) return;
		const name = KEY_NAMES[event.key.toLowerCase()];
		if (!name) return;
		event.preventDefault(); // arrows and space would scroll the page
		if (this.#held.has(name)) return; // auto-repeat: state unchanged
		this.#held.add(name);
		const sent = this.#publisher.send({ type: "keys", down: [...this.#held] });
		this.onPress?.(sent.seq, sent.sent_ms);
	};

	#keyup = (event: KeyboardEvent): void => {
		const name = KEY_NAMES[event.key.toLowerCase()];
		if (!name || !this.#held.delete(name)) return;
		this.#publisher.send({ type: "keys", down: [...this.#held] });
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
		this.#publisher.send({ type: "look", dx: this.#dx, dy: this.#dy });
		this.#dx = 0;
		this.#dy = 0;
	};
}

function isFormField(target: EventTarget | null): boolean {
	return target instanceof HTMLInputElement || target instanceof HTMLSelectElement || target instanceof HTMLTextAreaElement;
}
