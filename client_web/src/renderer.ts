// Draws decoded frames to the canvas once per display refresh.
// Why "newest wins": in game streaming a late frame is worth nothing; if the decoder
// outputs two frames between refreshes, the older one is closed unseen and counted
// as dropped instead of adding a refresh of latency.

export interface PresentedFrame {
	/** VideoFrame timestamp (us) = CMAF decode time = timing record pts_us. */
	ptsUs: number;
	width: number;
	height: number;
}

export class Renderer {
	readonly canvas: HTMLCanvasElement;
	readonly #ctx: CanvasRenderingContext2D;
	#next?: VideoFrame;
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
		if (this.#next) {
			this.#next.close();
			this.dropped++;
		}
		this.#next = frame;
	}

	#draw = (): void => {
		this.#raf = requestAnimationFrame(this.#draw);
		const frame = this.#next;
		if (!frame) return;
		this.#next = undefined;
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

	/** Forget a queued frame (on reconnect), keeping the last image on screen. */
	clear(): void {
		this.#next?.close();
		this.#next = undefined;
	}

	close(): void {
		cancelAnimationFrame(this.#raf);
		this.clear();
	}
}
