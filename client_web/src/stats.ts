// Rolling measurements for the overlay and the test hooks.
// Why bounded windows: a page left open for hours must not grow without limit, and the
// overlay shows recent behaviour (p50/p95 of the last samples), not all-time averages.

/** Nearest-rank percentile (p in [0, 100]) of a non-empty list. */
export function percentileOf(values: readonly number[], p: number): number {
	const sorted = [...values].sort((a, b) => a - b);
	const rank = Math.min(sorted.length - 1, Math.max(0, Math.ceil((p / 100) * sorted.length) - 1));
	return sorted[rank];
}

/** The latest `capacity` samples of one quantity, with percentiles. */
export class Window {
	readonly #values: number[] = [];
	constructor(readonly capacity = 600) {}

	push(value: number): void {
		if (!Number.isFinite(value)) return;
		this.#values.push(value);
		if (this.#values.length > this.capacity) this.#values.shift();
	}

	get samples(): number[] {
		return [...this.#values];
	}

	get count(): number {
		return this.#values.length;
	}

	/** Nearest-rank percentile (p in [0, 100]); undefined while empty. */
	percentile(p: number): number | undefined {
		return this.#values.length === 0 ? undefined : percentileOf(this.#values, p);
	}

	clear(): void {
		this.#values.length = 0;
	}
}

/** Frames per second over the last second of presentation times. */
export class FpsMeter {
	readonly #times: number[] = [];

	tick(nowMs: number): void {
		this.#times.push(nowMs);
		this.#trim(nowMs);
	}

	fps(nowMs: number): number {
		this.#trim(nowMs);
		return this.#times.length;
	}

	#trim(nowMs: number): void {
		while (this.#times.length > 0 && this.#times[0] <= nowMs - 1000) this.#times.shift();
	}
}

/** Server stages computed from the timing track: name -> [from stamp, to stamp]. */
export const SERVER_SPANS: ReadonlyArray<readonly [string, string, string]> = [
	// Same pairs as server/frames/timing.py STAGE_SPANS so the page and the server agree.
	["render", "render_start", "render_end"],
	["ring_r_handoff", "ring_r_ready", "upscale_start"],
	["upscale", "upscale_start", "upscale_end"],
	["ring_u_handoff", "ring_u_ready", "encode_start"],
	["encode", "encode_start", "encode_end"],
	["publish", "encode_end", "publish"],
];

/** Client stages the page measures itself, then the end-to-end total. */
export const CLIENT_STAGES = ["network", "decode", "present", "total"] as const;

/** Audio stages (client_web/src/audio_timing.ts AUDIO_SPANS) and the A/V offset at present. */
export const AUDIO_STAGES = [
	"audio_capture",
	"audio_encode",
	"audio_publish",
	"audio_network",
	"audio_decode",
	"audio_play",
	"audio_total",
	"av_offset",
] as const;

export const STAGES: readonly string[] = [...SERVER_SPANS.map(([name]) => name), ...CLIENT_STAGES, ...AUDIO_STAGES];

/** One Window per latency stage, in milliseconds. */
export class StageLatency {
	readonly windows = new Map<string, Window>(STAGES.map((name) => [name, new Window()]));

	add(stage: string, ms: number): void {
		this.windows.get(stage)?.push(ms);
	}

	summary(): Record<string, { p50?: number; p95?: number; n: number; samples: number[] }> {
		const out: Record<string, { p50?: number; p95?: number; n: number; samples: number[] }> = {};
		for (const [name, window] of this.windows) {
			out[name] = { p50: window.percentile(50), p95: window.percentile(95), n: window.count, samples: window.samples };
		}
		return out;
	}
}

type Summary = Record<string, { p50?: number; p95?: number; n: number; samples: number[] }>;

/** What the audio player's lip sync is made of (ms, and the playback offset in output
 * frames): defined here, below the player, so that the stats need not import it. */
export interface AudioSync {
	videoMs?: number;
	arrivalMs?: number;
	aheadMs?: number;
	targetMs?: number;
	offsetFrames?: number;
	contextMs: number;
}

/** What the player shows in its overlay and hands to the end-to-end tests (window.upcast). */
export interface Stats {
	status: string;
	connected: boolean;
	version?: string;
	subscribed: boolean;
	fps: number;
	framesReceived: number;
	framesDecoded: number;
	framesPresented: number;
	dropped: number;
	/** Video frames that never arrived: jumps in the fragments' mfhd sequence numbers. */
	framesLost: number;
	/** Frames received but dropped because an earlier one was missing (waiting for a keyframe). */
	skippedUndecodable: number;
	/** Video groups never received (gaps in the group sequence) or ended early (reset by the relay, abandoned). */
	groupsSkipped: number;
	/** Gaps of more than 200 ms between two frames on screen: how many, their total and the longest gap (ms). */
	freezes: number;
	freezeMs: number;
	longestFreezeMs: number;
	/** Frames dropped for being behind (renderer, decoder queue) or shown > 100 ms after arriving. */
	late: number;
	/** Video bytes received. */
	bytesReceived: number;
	/** Gaps in the timing track's publish counter (the timing track is rarely skipped: not a loss measure). */
	timingGaps: number;
	/** Keyframe recovery: waiting now (and why), requests sent, waits ended by a keyframe, the last one's ms. */
	recovery: { waiting: boolean; reason?: string; keyframeRequests: number; recoveries: number; lastRecoveryMs?: number; refetches: number };
	/** The video track playing (a rendition of the catalog), undefined between subscriptions. */
	rendition?: string;
	/** Moves from one rendition to another since the page loaded (not a track renamed by a new catalog). */
	renditionSwitches: number;
	/** Seconds each rendition has played since the page loaded. */
	renditionSeconds: Record<string, number>;
	/** How the rendition is chosen: mode "player" (a token: the catalog's first), "abr"
	 * (a spectator), "forced" (?rendition= or the page hook), "first" (?abr=off); the
	 * last reason, the switch waiting for its first frame, the ABR's throughput estimate
	 * and up-switch hold, the tracks chosen among, frames decoded only as references. */
	abr: {
		mode: string;
		pending?: string;
		reason?: string;
		estimateBps?: number;
		holdMs: number;
		failedUps: number;
		ladder: string[];
		lastSwitch?: { from: string; to: string; reason: string; tookMs?: number };
		hiddenFrames: number;
	};
	/** Feedback messages sent on the input track. */
	feedbackSent: number;
	/** Connections made to the relay (more than 1: the page reconnected). */
	connections: number;
	width: number;
	height: number;
	codec?: string;
	lastPresentedFrameId?: number;
	lastPresentedPtsUs?: number;
	/** Share of the last presented frames the server predicted (frame generation), 0..1. */
	predictedShare: number;
	/** What the server runs and why (adaptive quality), from the last presented frame's record. */
	quality?: {
		mode?: string;
		upscaler?: string;
		scale?: number;
		frameGeneration?: boolean;
		frameRate?: number;
		reason?: string;
	};
	inputsSent: number;
	inputPath: string;
	inputSubscribers: number;
	/** Per stage, in ms: render ... publish (server), network, decode, present, total. */
	latency: Summary;
	/** The audio path: packets received, decoded, what the worklet holds and misses. */
	audio: { enabled: boolean; running: boolean; muted: boolean; volume: number; packets: number; decoded: number; bufferedMs: number; underrunFrames: number; concealedFrames: number; decoderErrors: number; decoderRestarts: number; malformed: number; sync?: AudioSync; videoHeld: number; videoHeldMeanMs: number };
	/** Key press -> first frame showing it, ms. */
	inputToPhoton: { p50?: number; p95?: number; samples: number[] };
	errors: string[];
}
