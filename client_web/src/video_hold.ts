// Lip sync from the picture's side: a decoded frame waits (a few tens of ms at most)
// until the sound of its moment is about to be heard.
//
// Why: the sound cannot be played earlier than its arrival plus its jitter buffer plus
// what the output device renders ahead (42 ms in headless Chromium), while the picture
// is shown the moment it is decoded; on a fast path the picture is ahead of the sound
// by more than the +-40 ms people notice. The sound already waits for the picture when
// the picture is the late one (AudioPlayer.targetOffsetMs); this is the other half.
// Bounded by MAX_HOLD_MS: a game's picture never waits long for its sound, and not at
// all when the sound is muted or not playing. Why 100 ms: frames wait about 40 ms for
// their sound on a quiet machine (headless Chromium renders 42 ms ahead of what is
// heard); when the page is busy the sound's arrivals spread and it is scheduled later,
// and at 60 ms the picture could not follow (offsets of -57 to -75 ms for seconds
// beside one busy core; at 100 ms none over 40 ms in 3 runs).
export const SYNC_MS = 25; // aim this close (the output clock's reading jitters by ~5 ms)
export const MAX_HOLD_MS = 100;
const MAX_REMEMBERED = 64;

export class VideoHold {
	readonly #show: (frame: VideoFrame) => void;
	readonly #queue: { frame: VideoFrame; due: number; added: number }[] = [];
	// pts (us) -> ms the frame waited here, until the renderer reports it shown.
	readonly #waited = new Map<number, number>();
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
		this.#queue.push({ frame, due: Math.max(last, now + wait), added: now });
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
			while (this.#queue.length && this.#queue[0].due <= now + 1) {
				const { frame, added } = this.#queue.shift()!;
				this.#remember(frame.timestamp, now - added);
				this.#show(frame);
			}
			this.#schedule();
		}, delay);
	}

	/** How long the frame with ``ptsUs`` waited here (0: shown at once); read once.
	 * The sound's target follows the picture's latency *without* this wait: with it, a
	 * target that had risen once held the picture back, the held picture's latency held
	 * the target, and the pair stayed up (every step down smaller than the resync step):
	 * a run settled at 118 ms capture-to-heard and 99 ms render-to-present instead of
	 * 84 and 55. */
	waitedMs(ptsUs: number): number {
		const waited = this.#waited.get(ptsUs) ?? 0;
		this.#waited.delete(ptsUs);
		return waited;
	}

	#remember(ptsUs: number, waitedMs: number): void {
		this.#waited.set(ptsUs, waitedMs);
		// Frames the renderer drops are never read back: keep the map small.
		if (this.#waited.size > MAX_REMEMBERED) this.#waited.delete(this.#waited.keys().next().value!);
	}

	/** Drop what waits (a new subscription): frames are closed, not shown. */
	clear(): void {
		if (this.#timer !== undefined) clearTimeout(this.#timer);
		this.#timer = undefined;
		for (const { frame } of this.#queue.splice(0)) frame.close();
		this.#waited.clear();
	}
}
