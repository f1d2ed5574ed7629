// How far the sound's sync target waits for the picture.
//
// Audio with pts P is heard at page time P + target. It cannot be heard before its
// chunks are there (``earliest``: their arrival bound plus how far the worklet renders
// ahead); it waits for the picture when the picture is later (the picture's offset: the
// first quartile of the last frames shown, see VIDEO_WINDOW), unless the picture is so
// late (MAX_HOLD_MS) that it is catching up: a viewer that joined decodes the relay's
// cached group, up to a keyframe interval old, then skips ahead. The sound does not
// wait for that; it plays as early as it can and syncs once the picture has caught up.
//
// Once caught up, not at once: the picture must have been within MAX_HOLD_MS for
// SETTLE_MS. While a joining viewer catches up, each frame it shows is less late than
// the one before (seconds, then hundreds of ms, then live), and the window's first
// quartile passes through those frames as live ones fill it. For a frame or two it is
// up to 250 ms later than the sound could play, and the target jumped there and back:
// every move later is that much silence (nothing is due in the worklet until the new
// target), every move back a skip; a page whose frames come unevenly can go in and out
// of the hold more than once (the likely cause of the 0.4 s of silence the e2e join
// test heard 0.6-1 s after its gesture in fresh CI runs, where pages are slowest).
// client_web/test/follow_check.ts: 240 ms of silence at a join before, 30 now (the one
// move to a picture 30 ms late).
import { Window } from "./stats";

// A low quantile for the video: a viewer that joins first sees a burst of old frames
// (the relay's cached group, decoded at once), whose large offsets must not hold the
// sound back for as long as they are the median. And a window of 3 s (at 30 fps), not
// 1: after a stall of a loaded page its frames were shown 250 ms late for about a
// second, which moved the first quartile of 30 frames, so the sound jumped 245 ms
// later to wait for pictures that were on time again by then (|A/V| 180 ms for 1.5 s);
// the sound follows the picture only when most of 3 s of it is late.
export const VIDEO_WINDOW = 90; // presented frames the video offset is the first quartile of
const VIDEO_QUANTILE = 25;
// Video this much later than the sound could play is catching up.
export const MAX_HOLD_MS = 250;
// The picture within MAX_HOLD_MS this long before the sound follows it: a joining
// viewer's window is then a quarter live frames (10 of the 30-odd catch-up frames a
// page shows, at 15-30 fps), so its first quartile is the live picture's.
export const SETTLE_MS = 1000;

export class VideoFollow {
	readonly #offsets = new Window(VIDEO_WINDOW); // ms: present perf time - pts
	#withinSinceMs?: number; // since when the picture has been within MAX_HOLD_MS

	constructor(readonly settleMs = SETTLE_MS) {}

	/** A frame was ready to show at ``offsetMs`` (page time minus its pts, less what it
	 * waited for its sound). */
	presented(offsetMs: number): void {
		this.#offsets.push(offsetMs);
	}

	/** The picture's offset (ms): the first quartile of the last frames shown. */
	get videoMs(): number | undefined {
		return this.#offsets.percentile(VIDEO_QUANTILE);
	}

	/** The sync target (ms, page time minus pts) at page time ``nowMs``, for a sound
	 * that can be heard at ``earliestMs`` at the earliest. */
	target(earliestMs: number, nowMs: number): number {
		const video = this.videoMs;
		if (video === undefined || video - earliestMs > MAX_HOLD_MS) {
			this.#withinSinceMs = undefined;
			return earliestMs;
		}
		this.#withinSinceMs ??= nowMs;
		if (nowMs - this.#withinSinceMs < this.settleMs) return earliestMs;
		return Math.max(video, earliestMs);
	}

	/** Forget the frames shown (the subscription restarted). */
	clear(): void {
		this.#offsets.clear();
		this.#withinSinceMs = undefined;
	}
}
