// The game's sound: Opus (track `audio`, hang legacy container) -> WebCodecs
// AudioDecoder -> an AudioWorklet that plays each sample at the time its video frame
// is shown.
//
// Sync: a video frame with pts P can be shown at page time P + videoOffset (the
// pipeline's latency, read from the last shown frames less what each waited for its
// sound in VideoHold: their first quartile, see video_follow.ts). Audio with pts P is
// scheduled to be *heard* at the same P + videoOffset, which means holding it back:
// the audio of a moment arrives
// about when its frame does and video still has to decode and wait for a refresh. If
// audio ever arrives too late for that, it plays as early as its own jitter buffer
// allows instead (audio ahead of nothing is better than silence) and the A/V offset
// figure shows the difference.
// Browsers start an AudioContext only after a user gesture: the context is made at
// once (suspended) and resumed on the first click or key; the mute button is a gesture.
import { WORKLET_NAME, WORKLET_SOURCE } from "./audio_worklet";
import { ArrivalBound } from "./arrival_bound";
import { wallUs } from "./clock";
import { type AudioSync, Window } from "./stats";
import { VideoFollow } from "./video_follow";

export interface AudioRendition {
	track: string;
	codec: string;
	sampleRate: number;
	numberOfChannels: number;
	jitter?: number;
}

// A closed (errored) decoder is replaced at most this often.
const RESTART_MS = 100;
/** Audio jitter buffer: how far ahead of its arrival a chunk is scheduled at least. */
export const JITTER_MS = 20;
// A new target closer than this to the offset in use is ignored: every change is a
// (faded) jump, so it must be rare; 10 ms keeps sync well inside +-40 ms.
const RESYNC_MS = 10;
// The output clock's relation to page time (performanceTime - contextTime) is off by
// 10-20 ms in the first 30 ms after the context starts (headless Chromium), and then
// steady within 0.2 ms; a mapping made from a first reading kept that error (|A/V| 35-38
// ms instead of 19-21) until the target next moved. On a loaded machine the output
// device also loses time now and then (slips of 10-20 ms, the sound heard that much
// later for good). So the mapping is redone when the relation has slipped this far
// since it was made (also what a drifting device clock needs over hours).
const CLOCK_SLIP_MS = 5;
const MAX_RENDER_AHEAD_MS = 100;
// Chunks (3 s) whose arrivals bound the target (ArrivalBound: their 95th percentile,
// each stall of the page counted once). Why 3 s and not 1: a single stall of the page
// (70 ms, 7 chunks late) was 7 % of a 1 s window, so it moved the target 70 ms later
// for the next second (the picture, held at most VideoHold's MAX_HOLD_MS, cannot
// follow: A/V offsets of -70 to -90 ms, the p95 of whole runs); the chunks of that stall had
// missed their slots already, so the move bought nothing. Stalls that come every
// second or two still move it.
const LATE_WINDOW = 300;

/** Per-packet stamps the page adds, wall-clock microseconds. */
export interface AudioClientStamps {
	receive?: number;
	decode?: number;
	play?: number;
}

export class AudioPlayer {
	readonly context: AudioContext;
	readonly output: GainNode;
	#node?: AudioWorkletNode;
	#ready: Promise<void>;
	#decoder?: AudioDecoder;
	#rendition?: AudioRendition;
	#offsetFrames?: number; // what the worklet plays with (context frame - media frame)
	#targetMs?: number; // the target that offset was made for
	#mappedRunning = false; // whether it was mapped with the running output clock
	#mappedClockMs = 0; // the output clock's relation to page time it was mapped with
	readonly #video = new VideoFollow(); // how far the sound waits for the picture
	readonly #arrivals = new ArrivalBound(LATE_WINDOW); // ms: arrival perf time + jitter - pts
	readonly #renderAhead = new Window(LATE_WINDOW); // ms: see renderAheadMs
	// Input pts in decode order. Why not AudioData.timestamp: Chromium's Opus decoder
	// counts output samples from the first input's timestamp, so after any gap in the
	// input (a join, a skipped group, a paused source) its timestamps run late for good.
	// One Opus packet gives one output, in order, so the input's own pts is exact.
	readonly #pending: number[] = [];
	/** Audio pts (us) -> client stamps; read by the timing join. */
	onStamp?: (ptsUs: number, stage: keyof AudioClientStamps, wallUs: number) => void;
	packets = 0;
	decoded = 0;
	underrunFrames = 0;
	/** Output frames filled by loss concealment (a repeated pitch period, see the worklet). */
	concealedFrames = 0;
	/** Errors of the decoder (each closes it), the new decoders made after them, and
	 * frames too short to hold a timestamp and a packet. */
	decoderErrors = 0;
	decoderRestarts = 0;
	malformed = 0;
	#restartedMs = -Infinity;
	bufferedMs = 0;
	muted = false;
	volume = 0.8;
	/** Whether sound was already on when the latest gesture began (else it started it). */
	runningAtLastGesture = false;

	constructor() {
		this.context = new AudioContext({ latencyHint: "interactive", sampleRate: 48000 });
		this.output = this.context.createGain();
		this.output.connect(this.context.destination);
		this.#applyGain();
		const url = URL.createObjectURL(new Blob([WORKLET_SOURCE], { type: "text/javascript" }));
		this.#ready = this.context.audioWorklet.addModule(url).then(() => {
			const node = new AudioWorkletNode(this.context, WORKLET_NAME, { outputChannelCount: [1] });
			node.port.onmessage = (event) => this.#onReport(event.data);
			node.connect(this.output);
			this.#node = node;
			if (this.#offsetFrames !== undefined) node.port.postMessage({ type: "offset", offset: this.#offsetFrames });
		});
		const unlock = (): void => {
			this.runningAtLastGesture = this.running;
			void this.context.resume();
		};
		for (const type of ["pointerdown", "keydown", "touchend"]) window.addEventListener(type, unlock, { capture: true });
	}

	get running(): boolean {
		return this.context.state === "running";
	}

	setMuted(muted: boolean): void {
		this.muted = muted;
		this.#applyGain();
		if (!muted) void this.context.resume();
	}

	setVolume(volume: number): void {
		this.volume = Math.min(1, Math.max(0, volume));
		this.#applyGain();
	}

	#applyGain(): void {
		// A short ramp: a mute or volume step must not click either.
		this.output.gain.setTargetAtTime(this.muted ? 0 : this.volume, this.context.currentTime, 0.01);
	}

	configure(rendition: AudioRendition): void {
		if (this.#rendition?.track === rendition.track && this.#decoder?.state === "configured") return;
		this.#rendition = rendition;
		this.#makeDecoder(rendition);
	}

	#makeDecoder(rendition: AudioRendition): void {
		if (this.#decoder && this.#decoder.state !== "closed") this.#decoder.close();
		this.#pending.length = 0;
		this.#decoder = new AudioDecoder({
			output: (data) => this.#decodedData(data),
			error: (err) => {
				// WebCodecs closes a decoder after any error (a packet it cannot decode):
				// frame() makes a new one.
				this.decoderErrors++;
				console.warn("upcast: audio decoder:", err.message);
			},
		});
		this.#decoder.configure({ codec: rendition.codec, sampleRate: rendition.sampleRate, numberOfChannels: rendition.numberOfChannels });
	}

	/** One legacy frame: varint pts (us) + Opus packet. */
	frame(payload: Uint8Array): void {
		if (payload.length < 2 || payload.length <= 1 << (payload[0] >> 6)) {
			this.malformed++; // no room for a timestamp and a packet
			return;
		}
		if (this.#decoder?.state === "closed" && this.#rendition) {
			// An error closed it. Every Opus packet decodes on its own, so a new decoder
			// goes on from this one (the worklet conceals what was lost meanwhile), at
			// most once per RESTART_MS: a source that sends only garbage must not spin.
			const now = performance.now();
			if (now - this.#restartedMs < RESTART_MS) return;
			this.#restartedMs = now;
			this.decoderRestarts++;
			this.#makeDecoder(this.#rendition);
		}
		const decoder = this.#decoder;
		if (!decoder || decoder.state !== "configured") return;
		const [ptsUs, size] = readVarint(payload);
		const now = wallUs();
		this.packets++;
		this.#pending.push(ptsUs);
		this.onStamp?.(ptsUs, "receive", now);
		decoder.decode(new EncodedAudioChunk({ type: "key", timestamp: ptsUs, data: payload.subarray(size) }));
	}

	/** The subscription restarted: forget what is queued, keep the context. */
	reset(): void {
		this.#node?.port.postMessage({ type: "reset" });
		this.#arrivals.clear();
		this.#renderAhead.clear();
		this.#video.clear();
		this.#targetMs = undefined;
	}

	/** The video frame with pts ``ptsUs`` was ready to show at page time ``perfMs``:
	 * when it was shown, less what it waited for its sound (VideoHold.waitedMs). */
	videoPresented(ptsUs: number, perfMs: number): void {
		this.#video.presented(perfMs - ptsUs / 1000);
	}

	#decodedData(data: AudioData): void {
		const ptsUs = this.#pending.shift() ?? data.timestamp;
		const samples = new Float32Array(data.numberOfFrames);
		data.copyTo(samples, { planeIndex: 0, format: "f32-planar" });
		const rate = data.sampleRate;
		data.close();
		this.decoded++;
		const now = wallUs();
		this.onStamp?.(ptsUs, "decode", now);
		this.#arrivals.push(performance.now() + JITTER_MS - ptsUs / 1000);
		this.#renderAhead.push(this.renderAheadMs());
		this.#retarget();
		this.#node?.port.postMessage({ type: "chunk", start: Math.round((ptsUs * rate) / 1e6), data: samples }, [samples.buffer]);
	}

	/** The sync target's parts (ms, page time minus pts): for the stats and the tests. */
	syncParts(): AudioSync {
		return {
			videoMs: this.#video.videoMs,
			arrivalMs: this.#arrivals.bound(),
			aheadMs: this.#renderAhead.percentile(95),
			targetMs: this.#targetMs,
			offsetFrames: this.#offsetFrames,
			contextMs: this.context.currentTime * 1000,
		};
	}

	/** How far the worklet renders ahead of what is heard (ms): a sample must be in the
	 * worklet this long before its time to be heard, on top of the jitter buffer. The
	 * output timestamp says it (render clock minus the clock at the output); before
	 * the context runs, the context's own estimate. */
	renderAheadMs(): number {
		const ts = this.context.getOutputTimestamp();
		const estimate = (this.context.baseLatency + (this.context.outputLatency || 0)) * 1000;
		if (!this.running || !ts.contextTime) return estimate;
		const ahead = (this.context.currentTime - ts.contextTime) * 1000;
		// A stale output timestamp (a stalled device) must not push the sound seconds late.
		return Math.min(Math.max(ahead, 0), MAX_RENDER_AHEAD_MS);
	}

	/** Page time (ms) at which audio pts P should be heard, minus P. */
	targetOffsetMs(): number | undefined {
		const arrival = this.#arrivals.bound();
		if (arrival === undefined) return undefined;
		const earliest = arrival + this.#renderAhead.percentile(95)!;
		return this.#video.target(earliest, performance.now());
	}

	#retarget(): void {
		const target = this.targetOffsetMs();
		if (target === undefined) return;
		const running = this.running;
		// Compare targets, not sample offsets: the output clock's reading jitters by a
		// callback or two, and each change of offset is a (faded) jump, so only a real
		// move of the target, the context starting or its clock slipping may cause one.
		const ts = this.context.getOutputTimestamp();
		const clockMs = ts.performanceTime !== undefined && ts.contextTime !== undefined ? ts.performanceTime - ts.contextTime * 1000 : 0;
		if (
			this.#targetMs !== undefined &&
			this.#mappedRunning === running &&
			Math.abs(target - this.#targetMs) < RESYNC_MS &&
			(!this.#mappedRunning || Math.abs(clockMs - this.#mappedClockMs) < CLOCK_SLIP_MS)
		)
			return;
		let offset: number;
		if (!running || !ts.contextTime || !ts.performanceTime) {
			// Not playing yet (no gesture): map with the render clock; redone once it runs.
			offset = Math.round((this.context.currentTime + (target - performance.now()) / 1000) * this.context.sampleRate);
		} else {
			// The sample at context time C is heard at performanceTime + (C - contextTime).
			offset = Math.round((ts.contextTime + (target - ts.performanceTime) / 1000) * this.context.sampleRate);
		}
		this.#targetMs = target;
		this.#mappedRunning = running && !!ts.contextTime && !!ts.performanceTime;
		this.#mappedClockMs = clockMs;
		this.#offsetFrames = offset;
		this.#node?.port.postMessage({ type: "offset", offset });
	}

	/** How long a video frame with ``ptsUs``, decoded now, should wait for its sound to
	 * come within SYNC_MS of it (undefined: do not wait: no sound playing, muted). */
	videoWaitMs(ptsUs: number, syncMs: number): number | undefined {
		if (this.muted || !this.running || this.#targetMs === undefined || this.#offsetFrames === undefined) return undefined;
		return ptsUs / 1000 + this.#targetMs - performance.now() - syncMs;
	}

	/** Audio pts (ms) heard at page time ``perfMs``; undefined until audio plays. */
	audibleMsAt(perfMs: number): number | undefined {
		if (this.#offsetFrames === undefined || !this.running) return undefined;
		const ts = this.context.getOutputTimestamp();
		if (ts.contextTime === undefined || ts.performanceTime === undefined) return undefined;
		const contextFrame = (ts.contextTime + (perfMs - ts.performanceTime) / 1000) * this.context.sampleRate;
		return ((contextFrame - this.#offsetFrames) / this.context.sampleRate) * 1000;
	}

	#onReport(m: { offset: number; buffered: number; underrun: number; concealed: number; played: [number, number][] }): void {
		const rate = this.context.sampleRate;
		this.bufferedMs = (m.buffered / rate) * 1000;
		this.underrunFrames = m.underrun;
		this.concealedFrames = m.concealed;
		if (!this.running) return;
		const ts = this.context.getOutputTimestamp();
		if (ts.contextTime === undefined || ts.performanceTime === undefined) return;
		for (const [start, contextFrame] of m.played) {
			// Heard when its context frame reaches the output.
			const heardPerf = ts.performanceTime + (contextFrame / rate - ts.contextTime) * 1000;
			const ptsUs = Math.floor((start * 1e6) / rate); // the server's pts_us (floored)
			this.onStamp?.(ptsUs, "play", Math.round((performance.timeOrigin + heardPerf) * 1000));
		}
	}
}

function readVarint(bytes: Uint8Array): [number, number] {
	const first = bytes[0];
	const size = 1 << (first >> 6);
	let value = first & 0x3f;
	for (let i = 1; i < size; i++) value = value * 256 + bytes[i];
	return [value, size];
}
