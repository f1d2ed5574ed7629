// Draws decoded frames to the canvas once per display refresh.
// Why at most one frame of catch-up: in game streaming a late frame is worth little,
// so frames never queue up; but on a lossy link the frames behind a lost packet wait
// for its retransmission and then arrive together. With "newest wins" every such
// pair cost a frame (on 1-2 % loss, 14-16 % of the frames: the network bench's wifi
// and lte). Now two frames waiting are both shown, the older at this refresh and the
// newer at the next (one refresh, 17 ms at 60 Hz, later than it would have been); a
// third one waiting closes the oldest unseen, counted as dropped, and so does a second
// one still waiting a refresh later (the page is slower than the stream: no standing
// queue).

/** Frames waiting for a refresh: the one due now and one behind it. */
const MAX_WAITING = 2;

export interface PresentedFrame {
	/** VideoFrame timestamp (us) = CMAF decode time = timing record pts_us. */
	ptsUs: number;
	width: number;
	height: number;
}

export class Renderer {
	readonly canvas: HTMLCanvasElement;
	readonly #ctx: CanvasRenderingContext2D;
	// Oldest first; at most MAX_WAITING frames.
	readonly #waiting: VideoFrame[] = [];
	#behindLastTime = false;
	#raf = 0;
	presented = 0;
	dropped = 0;
	width = 0;
	height = 0;
	/** Called right after a frame is on the canvas (same task, so snapshots match it). */
	onPresent?: (frame: PresentedFrame) => void;

	constructor(canvas: HTMLCanvasElement) {
		this.canvas = canvas;
		const ctx = canvas.getContext("2d", { alpha: false, desynchronized: true });
		if (!ctx) throw new Error("2d canvas context unavailable");
		this.#ctx = ctx;
		this.#raf = requestAnimationFrame(this.#draw);
	}

	/** Queue a decoded frame; takes ownership. */
	push(frame: VideoFrame): void {
		this.#waiting.push(frame);
		while (this.#waiting.length > MAX_WAITING) {
			this.#waiting.shift()?.close();
			this.dropped++;
		}
	}

	#draw = (): void => {
		this.#raf = requestAnimationFrame(this.#draw);
		// Two waiting at two refreshes in a row: not a burst but a page slower than the
		// stream; catch up instead of keeping a standing frame of latency.
		const behind = this.#waiting.length >= MAX_WAITING;
		if (behind && this.#behindLastTime) {
			this.#waiting.shift()?.close();
			this.dropped++;
		}
		this.#behindLastTime = behind;
		const frame = this.#waiting.shift();
		if (!frame) return;
		const width = frame.displayWidth;
		const height = frame.displayHeight;
		// Resizing clears the canvas, so only do it when the stream's size changes.
		if (this.canvas.width !== width || this.canvas.height !== height) {
			this.canvas.width = width;
			this.canvas.height = height;
		}
		this.#ctx.drawImage(frame, 0, 0, width, height);
		const ptsUs = frame.timestamp;
		frame.close();
		this.presented++;
		this.width = width;
		this.height = height;
		this.onPresent?.({ ptsUs, width, height });
	};

	/** Forget the queued frames (on reconnect), keeping the last image on screen. */
	clear(): void {
		for (const frame of this.#waiting) frame.close();
		this.#waiting.length = 0;
	}

	close(): void {
		cancelAnimationFrame(this.#raf);
		this.clear();
	}
}
