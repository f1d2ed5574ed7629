// Per-packet audio latency: joins the server's audio timing records (``kind: "audio"``
// on the `timing` track, keyed by ``audio_pts_us``) with the page's receive, decode and
// play stamps, and measures the A/V offset at every presented video frame.
import type { AudioClientStamps } from "./audio";
import type { StageLatency } from "./stats";

export interface AudioTimingRecord {
	kind: "audio";
	audio_pts_us: number;
	stamps: Record<string, number>;
}

/** Audio stages: name -> [from, to], server stamps then the page's (same names in the overlay). */
export const AUDIO_SPANS: ReadonlyArray<readonly [string, string, string]> = [
	["audio_capture", "audio_sample", "audio_capture"],
	["audio_encode", "audio_encode_start", "audio_encode_end"],
	["audio_publish", "audio_encode_end", "audio_publish"],
	["audio_network", "audio_publish", "receive"],
	["audio_decode", "receive", "decode"],
	["audio_play", "decode", "play"],
	["audio_total", "audio_sample", "play"],
];

const KEEP = 512;

export class AudioTimingJoin {
	readonly #records = new Map<number, Record<string, number>>();
	readonly #client = new Map<number, AudioClientStamps>();
	readonly #latency: StageLatency;

	constructor(latency: StageLatency) {
		this.#latency = latency;
	}

	addRecord(record: AudioTimingRecord): void {
		this.#records.set(record.audio_pts_us, record.stamps);
		trim(this.#records);
		this.#maybeComplete(record.audio_pts_us);
	}

	stamp(ptsUs: number, stage: keyof AudioClientStamps, us: number): void {
		let client = this.#client.get(ptsUs);
		if (!client) {
			client = {};
			this.#client.set(ptsUs, client);
			trim(this.#client);
		}
		client[stage] = us;
		this.#maybeComplete(ptsUs);
	}

	#maybeComplete(ptsUs: number): void {
		const server = this.#records.get(ptsUs);
		const client = this.#client.get(ptsUs);
		if (!server || client?.play === undefined) return;
		const all: Record<string, number | undefined> = { ...server, ...client };
		for (const [name, from, to] of AUDIO_SPANS) {
			const a = all[from];
			const b = all[to];
			if (a !== undefined && b !== undefined) this.#latency.add(name, (b - a) / 1000);
		}
		this.#records.delete(ptsUs);
		this.#client.delete(ptsUs);
	}
}

function trim<K, V>(map: Map<K, V>): void {
	while (map.size > KEEP) map.delete(map.keys().next().value as K);
}
