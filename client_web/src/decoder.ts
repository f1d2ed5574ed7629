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
}

export interface DecoderEvents {
	/** A decoded frame; the receiver owns it and must close() it. */
	frame(frame: VideoFrame): void;
	error(message: string): void;
}

// A decoder that falls this far behind adds latency it never wins back: drop the rest
// of the group and resume at the next keyframe instead.
const MAX_DECODE_QUEUE = 8;

export class Decoder {
	readonly #events: DecoderEvents;
	#decoder?: VideoDecoder;
	#init?: Cmaf.InitSegment;
	#configKey = "";
	// Kept so the decoder can be rebuilt after an error without a new catalog.
	#pending?: VideoRendition;
	// After a gap or an error the decoder can only resume at a sync sample.
	#waitForKey = true;
	decoded = 0;
	skipped = 0;

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
				this.#events.frame(frame);
			},
			error: (err) => {
				// The decoder is closed after an error: make a new one at the next keyframe.
				this.#events.error(`decoder: ${err.message}`);
				this.#configKey = "";
				this.#waitForKey = true;
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
		this.#waitForKey = true;
	}

	/** Called when a group was skipped: frames after the gap reference missing ones. */
	gap(): void {
		this.#waitForKey = true;
	}

	/**
	 * Decode one moof+mdat. Returns the sample timestamps (us) handed to the decoder,
	 * so the caller can stamp their receive time; empty when skipped.
	 */
	decode(fragment: Uint8Array): number[] {
		if (this.#decoder?.state !== "configured" && this.#pending) this.configure(this.#pending);
		const decoder = this.#decoder;
		const init = this.#init;
		if (!decoder || !init || decoder.state !== "configured") return [];
		const out: number[] = [];
		for (const sample of Cmaf.decodeDataSegment(fragment, init)) {
			if (!sample.keyframe && decoder.decodeQueueSize > MAX_DECODE_QUEUE) this.#waitForKey = true;
			if (this.#waitForKey && !sample.keyframe) {
				this.skipped++;
				continue;
			}
			this.#waitForKey = false;
			decoder.decode(
				new EncodedVideoChunk({
					type: sample.keyframe ? "key" : "delta",
					timestamp: sample.timestamp,
					duration: sample.duration || undefined,
					data: sample.data,
				}),
			);
			out.push(sample.timestamp);
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
		this.#configKey = "";
		this.#pending = undefined;
		this.#waitForKey = true;
	}
}
