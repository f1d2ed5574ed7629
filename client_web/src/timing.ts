// Per-frame latency bookkeeping: joins the server's timing record (track `timing`)
// with the page's own receive/decode/present stamps by the video timestamp (pts_us).
// Why by pts: the VideoFrame that reaches the canvas only carries its timestamp, and
// the two tracks arrive independently, so either side may come first.
import { SERVER_SPANS, type StageLatency, Window } from "./stats";

/** The server's JSON per video frame (see /tmp/plan.md "Timing frame JSON"). */
export interface TimingRecord {
	frame: number;
	/** Publish counter: +1 per frame the session published; a gap is a lost frame. */
	n?: number;
	pts_us: number;
	keyframe?: boolean;
	predicted?: boolean;
	/** Last input seq the game applied before rendering this frame. */
	input_seq?: number;
	/** Game time the frame was rendered at, microseconds (absent when 0: unknown). */
	game_time_us?: number;
	/** What the server runs now (player controls follow it). */
	upscaler?: string;
	scale?: number;
	/** Whether the game renders every other frame and the server predicts the rest. */
	frame_generation?: boolean;
	/** The layer-cache policy of a cached upscaler (unet_cached), absent for the others. */
	cache_policy?: string;
	/** "game" (the built-in renderer) or "x11" (a captured application: colour only). */
	source?: string;
	/** Adaptive quality: "auto" or "fixed", and why the current setting was chosen. */
	quality?: string;
	quality_reason?: string;
	/** Frames per second the game renders now (adaptive quality may lower it). */
	frame_rate?: number;
	/** Wall-clock microseconds since the epoch, by stage label. */
	stamps: Record<string, number>;
}

/** What the page knows about one frame, stamps in wall-clock microseconds. */
interface ClientStamps {
	receive?: number;
	decode?: number;
	present?: number;
}

// Enough for a few seconds at 60 fps; older entries are dropped unmatched.
const KEEP = 512;

export class TimingJoin {
	readonly #records = new Map<number, TimingRecord>();
	readonly #client = new Map<number, ClientStamps>();
	readonly #latency: StageLatency;
	/** Called once per presented frame whose timing record is known. */
	onPresented?: (record: TimingRecord, presentUs: number) => void;
	/** Frames the server published that never reached us (gaps in `n`). */
	lost = 0;
	#lastN?: number;

	constructor(latency: StageLatency) {
		this.#latency = latency;
	}

	addRecord(record: TimingRecord): void {
		if (typeof record.n === "number") {
			if (this.#lastN !== undefined && record.n > this.#lastN + 1) this.lost += record.n - this.#lastN - 1;
			if (this.#lastN === undefined || record.n > this.#lastN) this.#lastN = record.n;
		}
		this.#records.set(record.pts_us, record);
		trim(this.#records);
		const client = this.#client.get(record.pts_us);
		if (client?.present !== undefined) this.#complete(record, client);
	}

	record(ptsUs: number): TimingRecord | undefined {
		return this.#records.get(ptsUs);
	}

	stamp(ptsUs: number, stage: keyof ClientStamps, us: number): void {
		let client = this.#client.get(ptsUs);
		if (!client) {
			client = {};
			this.#client.set(ptsUs, client);
			trim(this.#client);
		}
		client[stage] = us;
		if (stage === "present") {
			const record = this.#records.get(ptsUs);
			if (record) this.#complete(record, client);
		}
	}

	// Both halves known: add every stage once, then forget the frame.
	#complete(record: TimingRecord, client: ClientStamps): void {
		const s = record.stamps;
		for (const [name, from, to] of SERVER_SPANS) {
			if (s[from] !== undefined && s[to] !== undefined) this.#latency.add(name, (s[to] - s[from]) / 1000);
		}
		if (client.receive !== undefined && s.publish !== undefined) {
			this.#latency.add("network", (client.receive - s.publish) / 1000);
		}
		if (client.receive !== undefined && client.decode !== undefined) {
			this.#latency.add("decode", (client.decode - client.receive) / 1000);
		}
		if (client.decode !== undefined && client.present !== undefined) {
			this.#latency.add("present", (client.present - client.decode) / 1000);
		}
		if (client.present !== undefined && s.render_end !== undefined) {
			this.#latency.add("total", (client.present - s.render_end) / 1000);
		}
		this.#client.delete(record.pts_us);
		if (client.present !== undefined) this.onPresented?.(record, client.present);
	}

	reset(): void {
		this.#records.clear();
		this.#client.clear();
		this.#lastN = undefined; // a new subscription starts a new count
	}
}

function trim<K, V>(map: Map<K, V>): void {
	// Map iterates in insertion order: the first keys are the oldest.
	while (map.size > KEEP) {
		const oldest = map.keys().next().value as K;
		map.delete(oldest);
	}
}

/** Input-to-photon: key press sent_ms -> first presented frame with input_seq >= seq. */
export class InputToPhoton {
	readonly window = new Window(200);
	// Presses not yet seen on screen, oldest first.
	readonly #pending: { seq: number; sentMs: number }[] = [];

	press(seq: number, sentMs: number): void {
		this.#pending.push({ seq, sentMs });
		// A game that never echoes input_seq must not make this grow forever.
		if (this.#pending.length > 64) this.#pending.shift();
	}

	presented(record: TimingRecord, presentUs: number): void {
		const applied = record.input_seq;
		if (applied === undefined) return;
		while (this.#pending.length > 0 && this.#pending[0].seq <= applied) {
			const press = this.#pending.shift();
			if (press) this.window.push(presentUs / 1000 - press.sentMs);
		}
	}
}
