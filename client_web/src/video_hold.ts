// Lip sync from the picture's side: a decoded frame waits (a few tens of ms at most)
// until the sound of its moment is about to be heard.
//
// Why: the sound cannot be played earlier than its arrival plus its jitter buffer plus
// what the output device renders ahead (42 ms in headless Chromium), while the picture
// is shown the moment it is decoded; on a fast path the picture is ahead of the sound
// by more than the +-40 ms people notice. The sound already waits for the picture when
// the picture is the late one (AudioPlayer.targetOffsetMs); this is the other half.
// Bounded by MAX_HOLD_MS: a game's picture never waits long for its sound, and not at
// all when the sound is muted or not playing.
export const SYNC_MS = 25; // aim this close (the output clock's reading jitters by ~5 ms)
export const MAX_HOLD_MS = 60;

export class VideoHold {
	readonly #show: (frame: VideoFrame) => void;
	readonly #queue: { frame: VideoFrame; due: number }[] = [];
	#timer?: ReturnType<typeof setTimeout>;
	held = 0; // frames that waited
	heldMs = 0; // their total wait

	constructor(show: (frame: VideoFrame) => void) {
		this.#show = show;
	}

	/** Show ``frame`` now, or after ``waitMs`` (clamped to MAX_HOLD_MS), in order. */
	add(frame: VideoFrame, waitMs: number | undefined): void {
		const now = performance.now();
		const wait = Math.min(MAX_HOLD_MS, Math.max(0, waitMs ?? 0));
		if (wait <= 1 && this.#queue.length === 0) {
			this.#show(frame);
			return;
		}
		// Never before a frame queued earlier: frames stay in order.
		const last = this.#queue.at(-1)?.due ?? now;
		this.#queue.push({ frame, due: Math.max(last, now + wait) });
		this.held++;
		this.heldMs += wait;
		this.#schedule();
	}

	#schedule(): void {
		if (this.#timer !== undefined || this.#queue.length === 0) return;
		const delay = Math.max(0, this.#queue[0].due - performance.now());
		this.#timer = setTimeout(() => {
			this.#timer = undefined;
			const now = performance.now();
			while (this.#queue.length && this.#queue[0].due <= now + 1) this.#show(this.#queue.shift()!.frame);
			this.#schedule();
		}, delay);
	}

	/** Drop what waits (a new subscription): frames are closed, not shown. */
	clear(): void {
		if (this.#timer !== undefined) clearTimeout(this.#timer);
		this.#timer = undefined;
		for (const { frame } of this.#queue.splice(0)) frame.close();
	}
}
