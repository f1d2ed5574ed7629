// WebCodecs decoding of the CMAF `video` track.
// The init segment (ftyp+moov, base64 in the catalog) and each moof+mdat are parsed by
// @moq/hang's CMAF helpers: they give the avcC description, the timescale and, per
// fragment, the sample bytes, its decode time in microseconds and the sync flag.
import { Cmaf } from "@moq/hang/container";

export interface VideoRendition {
	/** Track name: the rendition's key in catalog.video.renditions. */
	track: string;
	codec: string;
	/** base64 ftyp+moov from catalog container.init. */
	init: string;
	codedWidth?: number;
	codedHeight?: number;
	/** Frames per second and rate cap (bit/s), when the catalog gives them (the ladder's rungs do). */
	framerate?: number;
	bitrate?: number;
}

export interface DecoderEvents {
	/** A decoded frame; the receiver owns it and must close() it. */
	frame(frame: VideoFrame): void;
	error(message: string): void;
	/** The decoder failed and closed itself: it is rebuilt at the next keyframe, which the caller should ask for. */
	needKey?(reason: string): void;
}

/** What one decode() call did. */
export interface Decoded {
	/** Sample timestamps (us) handed to the decoder. */
	timestamps: number[];
	/** Whether one of them was a keyframe. */
	keyframe: boolean;
}

// A decoder that falls this far behind adds latency it never wins back: drop the rest
// of the group and resume at the next keyframe instead.
const MAX_DECODE_QUEUE = 8;
// A catch-up floor this far ahead of the frames is another timeline (a new encoder
// counting from 0), not a replay to skip through: it is dropped.
const MAX_CATCH_UP_US = 5_000_000;
// The queue allowed while catching up: a replayed GOP of up to 2 s at 60 fps.
const CATCH_UP_QUEUE = 128;

export class Decoder {
	readonly #events: DecoderEvents;
	#decoder?: VideoDecoder;
	#init?: Cmaf.InitSegment;
	#configKey = "";
	// Kept so the decoder can be rebuilt after an error without a new catalog.
	#pending?: VideoRendition;
	// After a gap or an error the decoder can only resume at a sync sample.
	#waitForKey = true;
	// Why it waits: "behind" (its queue overflowed: what it drops is late, not lost).
	#waitReason = "start";
	decoded = 0;
	/** Frames dropped because something before them was missing (loss, skip, error). */
	skipped = 0;
	/** Frames dropped because the decoder fell behind (counted as late). */
	late = 0;
	/** Frames decoded only as references for later ones (catch-up after a switch), never shown. */
	hidden = 0;
	// Frames up to this pts (us) are decoded but not output: see catchUp().
	#catchUpUs?: number;

	constructor(events: DecoderEvents) {
		this.#events = events;
	}

	static supported(): boolean {
		return typeof VideoDecoder !== "undefined";
	}

	/** (Re)configure from the catalog; a no-op when nothing relevant changed. */
	configure(rendition: VideoRendition): void {
		const key = `${rendition.codec}|${rendition.init}`;
		if (key === this.#configKey && this.#decoder?.state === "configured") return;
		const initBytes = Uint8Array.from(atob(rendition.init), (c) => c.charCodeAt(0));
		this.#init = Cmaf.decodeInitSegment(initBytes);
		this.#close();
		this.#decoder = new VideoDecoder({
			output: (frame) => {
				this.decoded++;
				const floor = this.#catchUpUs;
				if (floor !== undefined && frame.timestamp <= floor) {
					this.hidden++;
					frame.close();
					return;
				}
				this.#catchUpUs = undefined;
				this.#events.frame(frame);
			},
			error: (err) => {
				// The decoder is closed after an error: make a new one at the next keyframe.
				this.#events.error(`decoder: ${err.message}`);
				this.#configKey = "";
				this.#wait("decoder error");
				this.#events.needKey?.("decoder error");
			},
		});
		this.#decoder.configure({
			codec: rendition.codec,
			description: this.#init.description,
			codedWidth: rendition.codedWidth,
			codedHeight: rendition.codedHeight,
			// Game streaming: one frame in, one frame out, no reordering buffer.
			optimizeForLatency: true,
		});
		this.#configKey = key;
		this.#pending = rendition;
		this.#wait("configured");
	}

	/**
	 * After a switch, the new track's first group is the relay's replay of its cached
	 * group, which starts up to a GOP before the picture already shown: its frames up to
	 * `ptsUs` are decoded (the later ones reference them) but not shown, and they may
	 * queue in the decoder beyond MAX_DECODE_QUEUE (a burst the decoder clears in a few
	 * ms per frame, not a decoder falling behind).
	 */
	catchUp(ptsUs: number | undefined): void {
		this.#catchUpUs = ptsUs !== undefined && Number.isFinite(ptsUs) ? ptsUs : undefined;
	}

	/** Frames were lost or a group skipped: frames after the gap reference missing ones. */
	gap(reason = "gap"): void {
		this.#wait(reason);
	}

	#wait(reason: string): void {
		if (!this.#waitForKey) this.#waitReason = reason;
		this.#waitForKey = true;
	}

	/** Whether frames are being dropped until the next keyframe, and why. */
	get waitingForKey(): boolean {
		return this.#waitForKey;
	}

	get waitReason(): string {
		return this.#waitReason;
	}

	/** The init segment's timescale (ticks per second), once configured. */
	get timescale(): number | undefined {
		return this.#init?.timescale;
	}

	/** A tfdt decode time in microseconds (the encoder's pts); undefined before the init segment. */
	ptsUs(decodeTime: number): number | undefined {
		const scale = this.#init?.timescale;
		if (!scale) return undefined;
		return scale === 1_000_000 ? decodeTime : Math.round((decodeTime * 1_000_000) / scale);
	}

	/**
	 * Decode one moof+mdat. Returns the sample timestamps (us) handed to the decoder,
	 * so the caller can stamp their receive time (empty when skipped), and whether a
	 * keyframe was among them. A decoder that closed itself on an error is rebuilt here.
	 */
	decode(fragment: Uint8Array): Decoded {
		if (this.#decoder?.state !== "configured" && this.#pending) this.configure(this.#pending);
		const decoder = this.#decoder;
		const init = this.#init;
		const out: Decoded = { timestamps: [], keyframe: false };
		if (!decoder || !init || decoder.state !== "configured") return out;
		for (const sample of Cmaf.decodeDataSegment(fragment, init)) {
			const floor = this.#catchUpUs;
			if (floor !== undefined && sample.timestamp < floor - MAX_CATCH_UP_US) this.#catchUpUs = undefined;
			// While catching up, the queue holds the replay: allow it and one group's worth more.
			const limit = this.#catchUpUs === undefined ? MAX_DECODE_QUEUE : CATCH_UP_QUEUE;
			if (!sample.keyframe && decoder.decodeQueueSize > limit) this.#wait("behind");
			if (this.#waitForKey && !sample.keyframe) {
				if (this.#waitReason === "behind") this.late++;
				else this.skipped++;
				continue;
			}
			this.#waitForKey = false;
			if (sample.keyframe) out.keyframe = true;
			decoder.decode(
				new EncodedVideoChunk({
					type: sample.keyframe ? "key" : "delta",
					timestamp: sample.timestamp,
					duration: sample.duration || undefined,
					data: sample.data,
				}),
			);
			out.timestamps.push(sample.timestamp);
		}
		return out;
	}

	get queueSize(): number {
		return this.#decoder?.decodeQueueSize ?? 0;
	}

	#close(): void {
		if (this.#decoder && this.#decoder.state !== "closed") this.#decoder.close();
		this.#decoder = undefined;
	}

	close(): void {
		this.#close();
		this.#catchUpUs = undefined;
		this.#configKey = "";
		this.#pending = undefined;
		this.#wait("closed");
	}
}
