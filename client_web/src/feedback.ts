// What the page receives, counted from the video track itself, and the `feedback`
// message that reports it to the session (server/session/feedback.py) on the input
// track every FEEDBACK_INTERVAL_MS.
//
// Why from the video track: the timing track is tiny and high-priority, so the relay
// rarely skips it and its gaps say nothing about lost pictures. The encoder numbers
// its fragments (mfhd) 1, 2, 3...: a jump is a frame that never arrived, whatever
// dropped it (relay skip-ahead, a group reset, the page abandoning a group).

// server/session/feedback.py FEEDBACK_INTERVAL_MS, FREEZE_MS, MAX_FEEDBACK_FRAMES;
// server/session/viewer_input.py MAX_MESSAGE_BYTES.
export const FEEDBACK_INTERVAL_MS = 250;
export const FREEZE_MS = 200;
export const MAX_FEEDBACK_FRAMES = 64;
const MAX_MESSAGE_BYTES = 2048;
// Room left for what the publisher adds (seq, sent_ms) and a margin.
const MAX_BODY_BYTES = MAX_MESSAGE_BYTES - 128;
/** A frame on screen later than this after its last byte arrived was shown late. */
export const LATE_MS = 100;
// Arrival times kept to judge lateness at present (a few seconds at 60 fps).
const KEEP_ARRIVALS = 256;

/** The body of a `feedback` message (type/seq/sent_ms are added when sent). */
export interface FeedbackBody {
	type: "feedback";
	player: boolean;
	/** [pts_us, arrival_ms (performance.now())] of frames that arrived since the last report. */
	frames: [number, number][];
	bytes: number;
	lost: number;
	skipped: number;
	freezes: number;
	freeze_ms: number;
	late: number;
}

/** Cumulative counters since the page first subscribed (never reset: the session takes differences). */
export class ReceiveStats {
	/** Video bytes received (whole fragments). */
	bytes = 0;
	/** Fragments received. */
	frames = 0;
	/** Frames that never arrived: jumps in the fragments' mfhd sequence numbers. */
	lost = 0;
	/** Groups not received, or ended before their last frame (reset or abandoned). */
	skipped = 0;
	/** Gaps of more than FREEZE_MS between two frames shown on screen, and their total ms. */
	freezes = 0;
	freezeMs = 0;
	/** Frames shown more than LATE_MS after their last byte arrived. */
	shownLate = 0;
	/** Longest gap between two shown frames so far, ms. */
	longestGapMs = 0;
	#lastSequence?: number;
	#lastShownMs?: number;
	#unreported: [number, number][] = [];
	readonly #arrivals = new Map<number, number>();

	/**
	 * One video fragment arrived whole at `arrivalMs` (performance.now()). Returns how
	 * many frames are missing right before it (0 when none or unknown).
	 */
	fragment(sequence: number | undefined, ptsUs: number | undefined, bytes: number, arrivalMs: number): number {
		this.bytes += bytes;
		this.frames++;
		let lost = 0;
		if (sequence !== undefined) {
			const last = this.#lastSequence;
			if (last !== undefined && sequence > last + 1) lost = sequence - last - 1;
			// A number at or below the last one: a new encoder (new size, restart) counts
			// from 1 again; nothing is lost, the count starts over.
			this.#lastSequence = sequence;
			this.lost += lost;
		}
		if (ptsUs !== undefined) {
			this.#unreported.push([ptsUs, Math.round(arrivalMs * 10) / 10]);
			if (this.#unreported.length > MAX_FEEDBACK_FRAMES) this.#unreported.shift();
			this.#arrivals.set(ptsUs, arrivalMs);
			if (this.#arrivals.size > KEEP_ARRIVALS) this.#arrivals.delete(this.#arrivals.keys().next().value as number);
		}
		return lost;
	}

	groupsSkipped(count: number): void {
		this.skipped += count;
	}

	/** A frame is on screen at `nowMs` (performance.now()). */
	shown(ptsUs: number, nowMs: number): void {
		const last = this.#lastShownMs;
		if (last !== undefined) {
			const gap = nowMs - last;
			if (gap > this.longestGapMs) this.longestGapMs = gap;
			if (gap > FREEZE_MS) {
				this.freezes++;
				this.freezeMs += gap;
			}
		}
		this.#lastShownMs = nowMs;
		const arrival = this.#arrivals.get(ptsUs);
		if (arrival !== undefined) {
			this.#arrivals.delete(ptsUs);
			if (nowMs - arrival > LATE_MS) this.shownLate++;
		}
	}

	/** Ms since the last frame was shown (0 before the first). */
	sinceShownMs(nowMs: number): number {
		return this.#lastShownMs === undefined ? 0 : nowMs - this.#lastShownMs;
	}

	/**
	 * A new subscription: the relay starts it at its newest group, so the fragment
	 * numbering and the on-screen continuity start over (the time between two
	 * subscriptions is a disconnection, not a freeze). The counters keep going.
	 */
	restart(): void {
		this.#lastSequence = undefined;
		this.#lastShownMs = undefined;
		this.#arrivals.clear();
	}

	/** Frames not reported yet, oldest first (at most MAX_FEEDBACK_FRAMES). */
	get unreported(): number {
		return this.#unreported.length;
	}

	/**
	 * The next report: frames since the last one and the counters; `late` is what the
	 * page dropped for being behind plus frames shown late. Takes the frames: a report
	 * made is a report sent.
	 */
	report(player: boolean, droppedLate: number): FeedbackBody {
		const body: FeedbackBody = {
			type: "feedback",
			player,
			frames: this.#unreported,
			bytes: this.bytes,
			lost: this.lost,
			skipped: this.skipped,
			freezes: this.freezes,
			freeze_ms: Math.round(this.freezeMs * 10) / 10,
			late: droppedLate + this.shownLate,
		};
		this.#unreported = [];
		// Far under the limit in practice (64 frames ~ 1.9 kB at worst); drop the oldest if not.
		while (body.frames.length > 0 && new TextEncoder().encode(JSON.stringify(body)).length > MAX_BODY_BYTES) {
			body.frames.shift();
		}
		return body;
	}
}
