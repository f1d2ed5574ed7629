// Asking the server for a keyframe when the picture cannot go on without one.
//
// After a skipped group, a lost frame or a decoder error, the frames that follow
// reference pictures the decoder never had: the player drops them until a keyframe.
// The encoder sends no periodic IDR (or rarely), so the player asks for one itself:
// at once, at most one request per REQUEST_INTERVAL_MS, and again every RETRY_MS
// while none arrives (the request or the keyframe may itself be lost).
//
// Sans-IO: time comes in as arguments; the player sends when poll() says so and
// calls poll() again after wakeIn() ms.
//
// A page without a token (a spectator) cannot ask: keyframe requests ride the input
// track, which needs one. It does not sit waiting either. With the rendition ladder a
// rung starts a group (an IDR) every ~1 s and the relay nudges the encoder for a
// keyframe when it skips a viewer, so one normally comes within LISTEN_WAIT_MS; and the
// ABR moves down on the skip, which subscribes a rung and so brings its cached group's
// keyframe sooner still. When none has come by then (a decoder error on the player's
// track, whose IDRs are ~10 s apart, with no ladder), poll() says to fetch the track's
// latest group again: the relay replays it from the keyframe that starts it
// (media.ts refetchVideo). `requests` stays 0 for such a page; `refetches` counts.

export const REQUEST_INTERVAL_MS = 500;
export const RETRY_MS = 1000;
/** A spectator waits this long for a keyframe before fetching the latest group again:
 * over the ladder's 1 s GOP and the relay's 1 s nudge interval, with a margin. */
export const LISTEN_WAIT_MS = 2500;
/** And again this often while none comes (each refetch replays up to a GOP). */
export const REFETCH_RETRY_MS = 5000;

export class KeyframeRecovery {
	/** Whether the page can ask the encoder for a keyframe (it has a token); if not,
	 * poll() asks for a refetch of the latest group instead, later. */
	readonly canRequest: boolean;
	/** Keyframe requests sent. */
	requests = 0;
	/** Refetches of the latest group asked for (pages that cannot request). */
	refetches = 0;
	/** Waits that ended with a keyframe, and how long the last one took (ms). */
	recoveries = 0;
	lastRecoveryMs?: number;
	/** Why the current (or last) wait began. */
	reason?: string;
	#since?: number;
	#lastRequest = Number.NEGATIVE_INFINITY;
	#due?: number;

	constructor(options: { canRequest?: boolean } = {}) {
		this.canRequest = options.canRequest ?? true;
	}

	/** What poll() returning true asks for: a keyframe request, or a refetch. */
	get action(): "request" | "refetch" {
		return this.canRequest ? "request" : "refetch";
	}

	/** Whether the player waits for a keyframe now. */
	get waiting(): boolean {
		return this.#since !== undefined;
	}

	/** Ms the current wait has lasted (0 when not waiting). */
	waitedMs(now: number): number {
		return this.#since === undefined ? 0 : now - this.#since;
	}

	/**
	 * The decoder needs a keyframe: ask at once (or when the rate limit allows). While
	 * already waiting nothing changes: the retry timer asks again if none comes.
	 */
	need(now: number, reason: string): void {
		if (this.#since !== undefined) return;
		this.#since = now;
		this.reason = reason;
		this.#due = this.canRequest ? Math.max(now, this.#lastRequest + REQUEST_INTERVAL_MS) : now + LISTEN_WAIT_MS;
	}

	/** A keyframe reached the decoder: the wait (if any) is over. */
	keyframe(now: number): void {
		if (this.#since !== undefined) {
			this.recoveries++;
			this.lastRecoveryMs = now - this.#since;
		}
		this.#since = undefined;
		this.#due = undefined;
	}

	/** Whether to act now (see `action`); true counts it and schedules the retry. */
	poll(now: number): boolean {
		if (this.#due === undefined || now < this.#due) return false;
		if (!this.canRequest) {
			this.refetches++;
			this.#due = now + REFETCH_RETRY_MS;
			return true;
		}
		this.#lastRequest = now;
		this.requests++;
		this.#due = now + RETRY_MS;
		return true;
	}

	/** Ms until poll() next has something to do; undefined when nothing is scheduled. */
	wakeIn(now: number): number | undefined {
		return this.#due === undefined ? undefined : Math.max(0, this.#due - now);
	}

	/** A new subscription starts at a group's keyframe: stop waiting, keep the counters. */
	reset(): void {
		this.#since = undefined;
		this.#due = undefined;
	}
}
