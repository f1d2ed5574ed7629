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

export const REQUEST_INTERVAL_MS = 500;
export const RETRY_MS = 1000;

export class KeyframeRecovery {
	/** Keyframe requests sent. */
	requests = 0;
	/** Waits that ended with a keyframe, and how long the last one took (ms). */
	recoveries = 0;
	lastRecoveryMs?: number;
	/** Why the current (or last) wait began. */
	reason?: string;
	#since?: number;
	#lastRequest = Number.NEGATIVE_INFINITY;
	#due?: number;

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
		this.#due = Math.max(now, this.#lastRequest + REQUEST_INTERVAL_MS);
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

	/** Whether to send a keyframe request now; true counts it and schedules the retry. */
	poll(now: number): boolean {
		if (this.#due === undefined || now < this.#due) return false;
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
