// How late the sound's chunks arrive, as the bound its sync target must cover.
//
// Each decoded chunk gives an arrival offset (page time it became playable less its
// pts, ms). The target must cover most of them, or chunks miss their slot and the
// worklet conceals them. The plain answer, the 95th percentile of the last 3 s, has
// one flaw: a single stall of the page (a garbage collection, a slow frame, the tests'
// own reads of the stats: 200-220 ms seen on a freshly started page) holds back every
// chunk that arrives meanwhile, and they all come out together. 22 chunks late by up
// to 220 ms are 7 % of the window, so that one stall moved the target 200 ms later for
// 3 s; the picture can wait at most VideoHold's 100 ms for its sound, so sound and
// picture were 100-150 ms apart until it aged out, and the chunks of that stall had
// missed their slots already: the move bought nothing.
//
// So a stall counts once. A run of consecutive late chunks (later than the window's
// median by more than LATE_MS) that is no longer than MAX_STALL_CHUNKS is one stall:
// it enters the 95th percentile as one value, its peak, while chunks that come late
// one at a time (jitter) or for longer (a step in the path's delay) count each. And
// stalls that recur still move the target: stalls less than MERGE_CHUNKS apart are
// one event (one hiccup often comes as two or three stalls within a few hundred ms:
// seen, 220 ms then 80 ms, 0.3 s apart), and with two or more events in the window the
// bound is at least the plain 95th percentile capped at the second-worst event's peak,
// as far as the smaller of two stalls a second apart; a lossy link's retransmissions
// (many events) are bounded as before. The same idea as the peak detector of WebRTC's
// NetEq, which raises its target only for delay peaks that repeat.
import { percentileOf as percentile } from "./stats";

/** Chunks later than the window's median by more than this belong to a burst (ms):
 * above the spread of a quiet page (+-6 ms), below one lost Opus frame and a half. */
export const LATE_MS = 15;
const QUANTILE = 95;
/** Consecutive late chunks up to this many (0.5 s of 10 ms chunks) are one stall;
 * longer, they are a new delay and count each. */
export const MAX_STALL_CHUNKS = 50;
/** Stalls this close (0.4 s) are one event. */
export const MERGE_CHUNKS = 40;

export class ArrivalBound {
	readonly #offsets: number[] = []; // ms, in arrival order

	constructor(readonly capacity: number) {}

	push(offsetMs: number): void {
		if (!Number.isFinite(offsetMs)) return;
		this.#offsets.push(offsetMs);
		if (this.#offsets.length > this.capacity) this.#offsets.shift();
	}

	clear(): void {
		this.#offsets.length = 0;
	}

	get count(): number {
		return this.#offsets.length;
	}

	/** The arrival offset (ms) the sync target must cover; undefined while empty. */
	bound(): number | undefined {
		const offsets = this.#offsets;
		if (offsets.length === 0) return undefined;
		const median = percentile(offsets, 50);
		const runs: { first: number; last: number; peak: number }[] = [];
		const counted: number[] = [];
		for (let i = 0; i < offsets.length; i++) {
			if (offsets[i] - median <= LATE_MS) {
				counted.push(offsets[i]);
				continue;
			}
			const run = runs.at(-1);
			if (run && run.last === i - 1) {
				run.last = i;
				run.peak = Math.max(run.peak, offsets[i]);
			} else runs.push({ first: i, last: i, peak: offsets[i] });
		}
		const events: number[] = []; // each event's peak
		let lastLate = -Infinity;
		for (const run of runs) {
			if (run.last - run.first < MAX_STALL_CHUNKS) counted.push(run.peak);
			else counted.push(...offsets.slice(run.first, run.last + 1));
			if (run.first - lastLate <= MERGE_CHUNKS) events[events.length - 1] = Math.max(events[events.length - 1], run.peak);
			else events.push(run.peak);
			lastLate = run.last;
		}
		const once = percentile(counted, QUANTILE);
		if (events.length < 2) return once;
		const secondWorst = events.sort((a, b) => b - a)[1];
		return Math.max(once, Math.min(percentile(offsets, QUANTILE), secondWorst));
	}
}
