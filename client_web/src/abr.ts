// Which rendition of the hang catalog a spectator plays, and when it moves (issue 44).
//
// Sans-IO, like the server's rate controller: fed what the page measures and `now`
// (performance.now() ms), it returns a decision (a track and its reason) or nothing;
// the player applies it (media.ts subscribes the new track and moves over at its
// first group). Each decision is one log line with its reason.
//
// The ladder. The catalog lists the player's track first (`video`, `video.N`: rate
// controlled for the player's link, intra refresh, an IDR only every ~10 s or on a
// request a spectator cannot send), then the spectator rungs (`video.<W>x<H>`, a fixed
// rate cap each, an IDR every ~1 s on the same frames on every rung). A spectator
// chooses among the rungs only (spectatorLadder): the player's track follows the
// player's link, not the spectator's, has no cap to measure headroom against, and its
// relay replay at a join or a switch is up to 10 s of the player's rate. With no
// rung (an older server, a ladder switched off) the first rendition is the ladder's
// only entry and nothing ever switches. `?rendition=<track>` still plays any track.
//
// Rules, and why (the names in capitals are DEFAULT_PARAMS' fields):
// - Start: the highest rung whose cap fits START_BUDGET_BPS, else the lowest. Nothing
//   is known about the link yet, and the relay replays the rung's latest group (up to
//   a GOP, ~1 s) at once: at 190 kbit/s that is ~25 kB, a picture within ~1 s even on
//   a 300 kbit/s link; a 750 kbit/s rung's ~100 kB would take 2.7 s there.
// - Down at once, one rung, on a group the relay skipped or reset (the link did not
//   carry the rung within the relay's latency bound), on a standing queue (the floor
//   of the one-way delay, arrival - pts, over the last FLOOR_MS above its minimum over
//   BASE_MS by QUEUE_DOWN_MS: every frame of the last 0.4 s was that late, so the link
//   carries less than the rung; the floor ignores a keyframe's spike and jitter), on
//   delivered fps clearly below the rung's frame rate while the frames that came were
//   made faster than they arrived (a slow game is not a slow link), on no frame for
//   STALL_MS, and on the decoder falling behind (frames dropped late). Down is never
//   held: a spectator's picture freezes while the link cannot carry it.
// - Up one rung only after a hold of stable playback (UP_HOLD_MS with none of the above
//   and no queue over QUEUE_SOFT_MS) and with headroom: the median of the throughput
//   samples of the last SAMPLE_AGE_MS at least UP_HEADROOM x the next rung's cap.
//   Samples come from bursts, the only times the link runs full (steady frames are
//   paced by the encoder and say nothing of headroom): a run of queued frames, each
//   ready at the sender before the one ahead of it had arrived (its pts plus the
//   smallest one-way delay seen, across switches, is before the previous arrival): the
//   relay's replay of a cached group at a join or a switch, a backlog on a link
//   narrower than the rung; its bytes over its time. Frames are judged CLASSIFY_MS
//   late, so that at a join the live frames after the replay have shown the delay's
//   floor. A run shorter than MIN_RUN_MS (frames handed over in one go) is the page
//   catching up after a stall, not the link: dropped. Keyframes much larger than the other frames give a
//   sample too (their extra bytes over their extra delay), but the rungs' encoders cap
//   every frame (a one-frame VBV), so on our stream they rarely do.
//   With no recent sample (a fast link whose replays arrive in one go, a stream with
//   no burst for SAMPLE_AGE_MS) the up-switch is itself the probe: the new rung's
//   replayed group is a burst that gives a sample, and a link that cannot carry it
//   fails it, which backs off. But not while the last sample, however old, said the
//   next rung does not fit, nor to a rung left for trouble (or whose up-switch failed),
//   until STALE_PROBE_MS after that: a narrow link is probed every two minutes at most
//   (each failed probe is a second of stutter), and a link that got better is found
//   within that.
// - Backoff: an up-switch followed by a down within FAIL_WINDOW_MS (or one whose
//   track never delivered) failed; the hold doubles, up to MAX_UP_HOLD_MS, so a link
//   that cannot carry the next rung is not probed every few seconds (each probe costs
//   a replayed group on top of the playing track). A rung held FAIL_WINDOW_MS halves it.
// - While a switch is pending (the new track subscribed, its first group not yet here)
//   no other up is taken; trouble cancels a pending up (down from the playing rung, or
//   back to it); a pending switch that delivers nothing in PENDING_TIMEOUT_MS is given up.
// - Inputs that are not finite numbers (NaN, Infinity, negative sizes) are ignored.

/** One rendition the ABR may choose. */
export interface Rung {
	track: string;
	/** Its rate cap, bit/s (the catalog's `bitrate`, or estimated from its pixels). */
	bitrate: number;
	width?: number;
	height?: number;
	framerate?: number;
}

/** What the catalog says about a video rendition (media.ts VideoRendition has these). */
export interface RenditionInfo {
	track: string;
	bitrate?: number;
	codedWidth?: number;
	codedHeight?: number;
	framerate?: number;
}

export interface AbrDecision {
	/** The track to play. */
	track: string;
	/** "up", "down", or "back" (a pending switch given up: stay on the playing track). */
	direction: "up" | "down" | "back";
	reason: string;
}

export interface AbrParams {
	startBudgetBps: number;
	upHeadroom: number;
	upHoldMs: number;
	maxUpHoldMs: number;
	failWindowMs: number;
	floorMs: number;
	baseMs: number;
	queueDownMs: number;
	queueSoftMs: number;
	fpsWindowMs: number;
	fpsDownRatio: number;
	stallMs: number;
	lateDownFrames: number;
	lateWindowMs: number;
	pendingTimeoutMs: number;
	sampleAgeMs: number;
	staleProbeMs: number;
	burstMinBytes: number;
}

export const DEFAULT_PARAMS: Readonly<AbrParams> = {
	// Under the 750 kbit/s half-size rung of a 720p display: a join starts on the
	// quarter-size one unless a rung this cheap exists above it.
	startBudgetBps: 500_000,
	// "Well above": the next rung's cap is a cap, its keyframes come in bursts, and the
	// samples are noisy; twice the cap leaves room for all three.
	upHeadroom: 2,
	upHoldMs: 4000,
	maxUpHoldMs: 64_000,
	failWindowMs: 10_000,
	floorMs: 400,
	baseMs: 10_000,
	// The relay resets a viewer's group when a frame waits past its latency bound; going
	// down at 120 ms of standing queue comes before that on a link a little too narrow
	// (a link at 80 % of the rung: about a second after it began), while a keyframe's
	// backlog or a retransmission drains within the floor's window.
	queueDownMs: 120,
	queueSoftMs: 50,
	fpsWindowMs: 2000,
	fpsDownRatio: 0.5,
	stallMs: 1500,
	// One decoder "behind" episode drops the rest of a group: a handful of frames.
	lateDownFrames: 5,
	lateWindowMs: 2000,
	pendingTimeoutMs: 3000,
	sampleAgeMs: 30_000,
	staleProbeMs: 120_000,
	// A burst of fewer bytes says little (a 190 kbit/s rung's replayed group is up to
	// ~25 kB, half that on average).
	burstMinBytes: 4000,
};

// Bits per pixel per frame of a rung without a `bitrate` in the catalog: about what
// the server's default_bitrate gives (6 Mbit/s at 720p60 is 0.11).
const ESTIMATE_BPP = 0.1;
// A frame ready this much before the previous one arrived was queued behind it.
const QUEUED_MARGIN_MS = 15;
// Frames are judged this long after they arrive (see the rules above).
const CLASSIFY_MS = 500;
const BURST_MIN_FRAMES = 3;
// A run faster than this was handed over in one go after a stall of the page, not
// timed by the link.
const MIN_RUN_MS = 2;
// A long backlog gives a sample every this much.
const MAX_RUN_MS = 1000;
const MIN_KEY_MS = 2;
const MAX_SAMPLES = 7;
// The one-way delay's floor across switches, for the queued test: kept per second.
const LINK_BASE_MS = 30_000;
// A delay or pts jump this large is a new timeline (an encoder restart), not a queue.
const TIMELINE_JUMP_MS = 10_000;

const finite = (x: unknown): x is number => typeof x === "number" && Number.isFinite(x);

/**
 * The renditions a spectator chooses among: the rungs (every rendition after the
 * first, the player's track), cheapest first; the first rendition alone when there is
 * no rung. A rung without a `bitrate` is priced from its pixels.
 */
export function spectatorLadder(renditions: readonly RenditionInfo[]): Rung[] {
	const pool = renditions.length > 1 ? renditions.slice(1) : renditions.slice(0, 1);
	const rungs = pool.map(
		(r): Rung => ({
			track: r.track,
			bitrate: finite(r.bitrate) && r.bitrate > 0 ? r.bitrate : estimatedBitrate(r),
			width: r.codedWidth,
			height: r.codedHeight,
			framerate: finite(r.framerate) && r.framerate > 0 ? r.framerate : undefined,
		}),
	);
	return rungs.sort((a, b) => a.bitrate - b.bitrate || (a.width ?? 0) * (a.height ?? 0) - (b.width ?? 0) * (b.height ?? 0));
}

function estimatedBitrate(r: RenditionInfo): number {
	const w = finite(r.codedWidth) ? r.codedWidth : 0;
	const h = finite(r.codedHeight) ? r.codedHeight : 0;
	const fps = finite(r.framerate) && r.framerate > 0 ? r.framerate : 30;
	return w > 0 && h > 0 ? ESTIMATE_BPP * w * h * fps : 0;
}

/** How the page picks its rendition, from its URL: `?rendition=<track>` forces one
 * (no ABR), `?abr=off` keeps the catalog's first. */
export function renditionParams(search: string): { forced?: string; abrOff: boolean } {
	const query = new URLSearchParams(search);
	const forced = query.get("rendition") || undefined;
	const abr = (query.get("abr") ?? "").toLowerCase();
	return { forced, abrOff: abr === "off" || abr === "0" || abr === "false" };
}

/** "1.5 Mbit/s", "190 kbit/s". */
export function formatBps(bps: number): string {
	return bps >= 1e6 ? `${(bps / 1e6).toFixed(1)} Mbit/s` : `${Math.round(bps / 1e3)} kbit/s`;
}

interface Arrival {
	t: number;
	owd: number;
	ptsMs: number;
	bytes: number;
}

export class Abr {
	readonly params: AbrParams;
	#ladder: Rung[] = [];
	#playing?: string;
	#target?: string;
	#pendingSince?: number;
	#pendingUp = false;
	/** Switches made (the new track's first group arrived and the page moved over). */
	switches = 0;
	/** Why the last decision was taken. */
	reason?: string;
	/** Up-switches that failed soon (each doubled the hold). */
	failedUps = 0;
	#holdMs: number;
	#stableSince = 0;
	#lastUpAt?: number;
	// One-way delays (and arrival times, pts) of the playing track since the last switch.
	#arrivals: Arrival[] = [];
	#lastFrameAt?: number;
	#stallReported = false;
	#fpsReportedAt = Number.NEGATIVE_INFINITY;
	// The cap of the rung played last: a catalog that renames the tracks keeps the cost.
	#lastBitrate?: number;
	#run?: { startT: number; lastT: number; bytes: number; frames: number };
	// Frames not judged yet (queued or not), oldest first, and the last one judged.
	#unjudged: Arrival[] = [];
	#judged?: Arrival;
	// Per second: the smallest one-way delay (across switches).
	#floors: { sec: number; owd: number }[] = [];
	#samples: { t: number; bps: number }[] = [];
	// The last sample, kept past SAMPLE_AGE_MS, and when each rung was last left for
	// trouble (or failed to be reached): they hold blind probes back (rules above).
	#lastSample?: { t: number; bps: number };
	readonly #troubleAt = new Map<string, number>();
	#lastLate?: number;
	#late: { t: number; n: number }[] = [];

	constructor(params: Partial<AbrParams> = {}) {
		const clean = Object.fromEntries(Object.entries(params).filter(([, v]) => finite(v) && v >= 0));
		this.params = { ...DEFAULT_PARAMS, ...clean };
		this.#holdMs = this.params.upHoldMs;
	}

	get ladder(): readonly Rung[] {
		return this.#ladder;
	}

	/** The track playing now (undefined before the first choice). */
	get playing(): string | undefined {
		return this.#playing;
	}

	/** The track the ABR wants: the playing one, or the one a pending switch goes to. */
	get target(): string | undefined {
		return this.#target;
	}

	get pending(): string | undefined {
		return this.#target !== this.#playing ? this.#target : undefined;
	}

	/** The current up-switch hold, ms. */
	get holdMs(): number {
		return this.#holdMs;
	}

	/** The link's throughput estimate (bit/s): the median of the recent burst samples. */
	estimate(now: number): number | undefined {
		this.#samples = this.#samples.filter((s) => now - s.t <= this.params.sampleAgeMs);
		if (this.#samples.length === 0) return undefined;
		const sorted = this.#samples.map((s) => s.bps).sort((a, b) => a - b);
		const mid = sorted.length >> 1;
		return sorted.length % 2 ? sorted[mid] : (sorted[mid - 1] + sorted[mid]) / 2;
	}

	/**
	 * A catalog (the first, or a new one). Returns the track to play now: the start
	 * choice, the playing (or pending) track while it is still listed, else the rung
	 * nearest the old one in cost (a new encoded size renamed the tracks).
	 */
	setLadder(rungs: readonly Rung[], now: number): string | undefined {
		this.#ladder = rungs.filter((r) => typeof r.track === "string" && finite(r.bitrate));
		if (this.#ladder.length === 0) return undefined;
		const has = (track?: string): boolean => track !== undefined && this.#index(track) >= 0;
		if (has(this.#playing)) {
			if (!has(this.#target)) this.#cancelPending(now, `${this.#target} left the catalog`);
			return this.#target;
		}
		let choice: Rung;
		if (this.#playing === undefined) {
			const fits = this.#ladder.filter((r) => r.bitrate <= this.params.startBudgetBps);
			choice = fits.at(-1) ?? this.#ladder[0];
			this.reason = `start: ${fits.length ? `the highest rung under ${formatBps(this.params.startBudgetBps)}` : "the lowest rung"}`;
		} else {
			const old = this.#lastBitrate ?? 0;
			choice = this.#ladder.filter((r) => r.bitrate <= old).at(-1) ?? this.#ladder[0];
			this.reason = `catalog changed: ${this.#playing} is gone`;
		}
		this.#playing = choice.track;
		this.#target = choice.track;
		this.#pendingSince = undefined;
		this.#lastBitrate = choice.bitrate;
		this.#resetMeasures(now);
		return choice.track;
	}

	/** A new subscription epoch (reconnect, broadcast back): choose from scratch, keep
	 * what was learnt about up-switches (hold, samples). */
	restart(): void {
		this.#playing = undefined;
		this.#target = undefined;
		this.#pendingSince = undefined;
		this.#lastBitrate = undefined;
		this.#arrivals = [];
		this.#run = undefined;
		this.#unjudged = [];
		this.#judged = undefined;
		this.#floors = [];
		this.#lastFrameAt = undefined;
		this.#lastLate = undefined;
		this.#late = [];
	}

	/** The page moved over to `track` (its first group arrived). */
	switched(now: number, track: string): void {
		if (!finite(now) || this.#index(track) < 0) return;
		const from = this.#playing === undefined ? -1 : this.#index(this.#playing);
		const up = from >= 0 && this.#index(track) > from;
		if (track !== this.#playing) this.switches++;
		this.#playing = track;
		this.#target = track;
		this.#pendingSince = undefined;
		this.#pendingUp = false;
		this.#lastBitrate = this.#ladder[this.#index(track)].bitrate;
		this.#lastUpAt = up ? now : undefined;
		this.#resetMeasures(now);
	}

	/** The pending switch to `track` ended without a frame (no such track, refused). */
	switchFailed(now: number, track: string, why: string): void {
		if (track !== this.#target || track === this.#playing) return;
		this.#cancelPending(finite(now) ? now : this.#stableSince, `switch to ${track} failed: ${why}`);
	}

	/**
	 * One frame of the playing track arrived whole at `now`: its size, its pts (us),
	 * whether it is a keyframe.
	 */
	frame(now: number, bytes: number, ptsUs: number, keyframe = false): AbrDecision | undefined {
		if (!finite(now) || !finite(bytes) || bytes < 0 || !finite(ptsUs) || this.#playing === undefined) return undefined;
		const ptsMs = ptsUs / 1000;
		const owd = now - ptsMs;
		const last = this.#arrivals.at(-1) ?? this.#unjudged.at(-1);
		if (last && (ptsMs < last.ptsMs - TIMELINE_JUMP_MS || Math.abs(owd - last.owd) > TIMELINE_JUMP_MS)) {
			// A new timeline: what was measured no longer compares.
			this.#resetMeasures(now);
			this.#unjudged = [];
			this.#judged = undefined;
			this.#floors = [];
		}
		this.#lastFrameAt = now;
		this.#stallReported = false;
		const base = this.#minOwd(now - this.params.baseMs);
		if (keyframe && base !== undefined && this.#arrivals.length >= 10) {
			// The minimum delay includes a small frame's own transfer: count only the bytes
			// the keyframe has over such a frame.
			const small = Math.min(...this.#arrivals.map((a) => a.bytes));
			if (bytes > 2 * small) this.#sample(now, ((bytes - small) * 8) / (Math.max(MIN_KEY_MS, owd - base) / 1000));
		}
		const arrival = { t: now, owd, ptsMs, bytes };
		this.#arrivals.push(arrival);
		this.#floor(now, owd);
		this.#unjudged.push(arrival);
		while (this.#unjudged.length > 0 && now - this.#unjudged[0].t >= CLASSIFY_MS) this.#judge(this.#unjudged.shift()!);
		const cut = now - this.params.baseMs;
		while (this.#arrivals.length > 0 && this.#arrivals[0].t < cut) this.#arrivals.shift();
		const queue = this.#queueMs(now);
		if (queue !== undefined && queue > this.params.queueDownMs) {
			return this.#down(now, `delay growing: ${queue.toFixed(0)} ms over its minimum for ${this.params.floorMs} ms`);
		}
		if (queue !== undefined && queue > this.params.queueSoftMs) this.#stableSince = now;
		return this.#maybeUp(now);
	}

	/** A video group was skipped or reset (the relay left this viewer behind). */
	skipped(now: number, why = "group skipped"): AbrDecision | undefined {
		if (!finite(now)) return undefined;
		return this.#down(now, why);
	}

	/** The decoder's count of frames dropped for being behind (cumulative). */
	late(now: number, total: number): AbrDecision | undefined {
		if (!finite(now) || !finite(total)) return undefined;
		const last = this.#lastLate;
		this.#lastLate = total;
		if (last === undefined || total <= last) return undefined;
		this.#late.push({ t: now, n: total - last });
		this.#late = this.#late.filter((e) => now - e.t <= this.params.lateWindowMs);
		const n = this.#late.reduce((sum, e) => sum + e.n, 0);
		this.#stableSince = now;
		if (n < this.params.lateDownFrames) return undefined;
		this.#late = [];
		return this.#down(now, `decoder behind: ${n} frames dropped late in ${this.params.lateWindowMs / 1000} s`);
	}

	/** Timers: a stall, a pending switch that never came, low fps, an up-switch due. */
	poll(now: number): AbrDecision | undefined {
		if (!finite(now) || this.#playing === undefined) return undefined;
		if (this.#pendingSince !== undefined && now - this.#pendingSince > this.params.pendingTimeoutMs) {
			const track = this.#target;
			this.#cancelPending(now, `switch to ${track} timed out (${this.params.pendingTimeoutMs} ms without a frame)`);
			return { track: this.#playing, direction: "back", reason: this.reason ?? "" };
		}
		if (this.#lastFrameAt !== undefined && !this.#stallReported && now - this.#lastFrameAt > this.params.stallMs) {
			this.#stallReported = true;
			return this.#down(now, `no frame for ${((now - this.#lastFrameAt) / 1000).toFixed(1)} s`);
		}
		const fps = this.#fpsTrouble(now);
		if (fps) return this.#down(now, fps);
		return this.#maybeUp(now);
	}

	// ---- decisions

	#maybeUp(now: number): AbrDecision | undefined {
		if (this.#lastUpAt !== undefined && now - this.#lastUpAt >= this.params.failWindowMs) {
			// The rung held: the backoff halves (a link that failed before is still
			// remembered for a while, so a rung that holds 10 s of every 30 is not retried
			// every few seconds).
			this.#lastUpAt = undefined;
			this.#holdMs = Math.max(this.params.upHoldMs, this.#holdMs / 2);
		}
		if (this.pending !== undefined || this.#playing === undefined) return undefined;
		const i = this.#index(this.#playing);
		if (i < 0 || i + 1 >= this.#ladder.length) return undefined;
		if (now - this.#stableSince < this.#holdMs) return undefined;
		const estimate = this.estimate(now);
		const next = this.#ladder[i + 1];
		const fits = (bps: number): boolean => bps >= this.params.upHeadroom * next.bitrate;
		const stable = `after ${(this.#holdMs / 1000).toFixed(0)} s stable`;
		if (estimate === undefined) {
			const last = this.#lastSample;
			if (last && !fits(last.bps) && now - last.t < this.params.staleProbeMs) return undefined;
			if (now - (this.#troubleAt.get(next.track) ?? Number.NEGATIVE_INFINITY) < this.params.staleProbeMs) return undefined;
			const why = last ? `the last throughput measured, ~${formatBps(last.bps)}, is ${((now - last.t) / 1000).toFixed(0)} s old` : "no throughput measured yet";
			return this.#decide(now, next.track, "up", `up: probing, ${why}, ${stable}`);
		}
		if (!fits(estimate)) return undefined;
		const reason = `up: throughput ~${formatBps(estimate)} >= ${this.params.upHeadroom} x ${formatBps(next.bitrate)} ${stable}`;
		return this.#decide(now, next.track, "up", reason);
	}

	#down(now: number, why: string): AbrDecision | undefined {
		this.#stableSince = now;
		if (this.#playing === undefined) return undefined;
		const i = this.#index(this.#playing);
		if (i < 0) return undefined;
		const pending = this.pending === undefined ? -1 : this.#index(this.pending);
		if (pending >= 0 && pending < i) return undefined; // a lower rung is on its way
		// Trouble soon after an up-switch, or while probing up: the up failed.
		const recentUp = this.#lastUpAt !== undefined && now - this.#lastUpAt < this.params.failWindowMs;
		if (recentUp || pending > i) this.#failedUp(now);
		if (pending > i) this.#troubleAt.set(this.#ladder[pending].track, now);
		if (i === 0) {
			if (pending < 0) return undefined; // the lowest rung: nothing lower to go to
			return this.#decide(now, this.#playing, "back", `${why}: stay on ${this.#playing}`);
		}
		this.#troubleAt.set(this.#playing, now);
		return this.#decide(now, this.#ladder[i - 1].track, "down", `down: ${why}`);
	}

	#decide(now: number, track: string, direction: AbrDecision["direction"], reason: string): AbrDecision {
		this.#target = track;
		this.#pendingSince = track === this.#playing ? undefined : now;
		this.#pendingUp = direction === "up";
		this.reason = reason;
		return { track, direction, reason };
	}

	#failedUp(now: number): void {
		this.#lastUpAt = undefined;
		this.#pendingUp = false;
		this.failedUps++;
		this.#holdMs = Math.min(this.params.maxUpHoldMs, this.#holdMs * 2);
		this.#stableSince = now;
	}

	#cancelPending(now: number, why: string): void {
		if (this.#pendingUp) {
			this.#failedUp(now);
			if (this.#target !== undefined) this.#troubleAt.set(this.#target, now);
		}
		this.#target = this.#playing;
		this.#pendingSince = undefined;
		this.#pendingUp = false;
		this.reason = why;
		this.#stableSince = now;
	}

	// ---- measures

	#index(track: string): number {
		return this.#ladder.findIndex((r) => r.track === track);
	}

	#resetMeasures(now: number): void {
		this.#arrivals = [];
		this.#lastFrameAt = now;
		this.#stallReported = false;
		this.#stableSince = now;
		this.#late = [];
	}

	#minOwd(since: number): number | undefined {
		let min: number | undefined;
		for (const a of this.#arrivals) if (a.t >= since && (min === undefined || a.owd < min)) min = a.owd;
		return min;
	}

	/** The standing queue: the delay floor of the last FLOOR_MS over the minimum since
	 * the switch (up to BASE_MS); undefined until FLOOR_MS of frames are there. */
	#queueMs(now: number): number | undefined {
		const first = this.#arrivals[0];
		if (!first || now - first.t < this.params.floorMs) return undefined;
		const floor = this.#minOwd(now - this.params.floorMs);
		const base = this.#minOwd(-Infinity);
		return floor === undefined || base === undefined ? undefined : floor - base;
	}

	#floor(now: number, owd: number): void {
		const sec = Math.floor(now / 1000);
		const last = this.#floors.at(-1);
		if (last?.sec === sec) last.owd = Math.min(last.owd, owd);
		else this.#floors.push({ sec, owd });
		while (this.#floors.length > 0 && this.#floors[0].sec < sec - LINK_BASE_MS / 1000) this.#floors.shift();
	}

	/** Frames arrive back to back only when they queued somewhere: time such runs. A
	 * frame is queued when it was ready (its pts plus the delay's floor) before the
	 * previous frame had arrived. */
	#judge(frame: Arrival): void {
		const prev = this.#judged;
		this.#judged = frame;
		let base = Number.POSITIVE_INFINITY;
		for (const f of this.#floors) base = Math.min(base, f.owd);
		const queued = prev !== undefined && frame.ptsMs > prev.ptsMs && frame.ptsMs + base + QUEUED_MARGIN_MS < prev.t;
		const run = this.#run;
		if (queued) {
			// The run is timed from its first frame's arrival: that frame's own bytes may
			// have been on the way before, so they do not count.
			if (!run) {
				this.#run = { startT: frame.t, lastT: frame.t, bytes: 0, frames: 1 };
				return;
			}
			run.lastT = frame.t;
			run.bytes += frame.bytes;
			run.frames++;
			if (run.lastT - run.startT < MAX_RUN_MS) return;
			this.#run = { startT: frame.t, lastT: frame.t, bytes: 0, frames: 1 }; // a long backlog: sample, go on
		} else {
			this.#run = undefined;
			if (!run) return;
		}
		const ms = run.lastT - run.startT;
		if (run.frames >= BURST_MIN_FRAMES && run.bytes >= this.params.burstMinBytes && ms >= MIN_RUN_MS) {
			this.#sample(frame.t, (run.bytes * 8) / (ms / 1000));
		}
	}

	#sample(now: number, bps: number): void {
		if (!finite(bps) || bps <= 0) return;
		this.#samples.push({ t: now, bps });
		this.#lastSample = { t: now, bps };
		if (this.#samples.length > MAX_SAMPLES) this.#samples.shift();
	}

	/** Delivered fps clearly under the rung's rate, while the frames that did arrive were
	 * made faster than they arrived: the link, not the game, is short. */
	#fpsTrouble(now: number): string | undefined {
		const rung = this.#ladder[this.#index(this.#playing ?? "")];
		const rate = rung?.framerate;
		const first = this.#arrivals[0];
		if (!rate || !first || now - first.t < this.params.fpsWindowMs) return undefined;
		if (now - this.#fpsReportedAt < this.params.fpsWindowMs) return undefined; // once per window
		const window = this.#arrivals.filter((a) => a.t > now - this.params.fpsWindowMs);
		const fps = (window.length * 1000) / this.params.fpsWindowMs;
		if (fps >= this.params.fpsDownRatio * rate) return undefined;
		// Media time delivered per wall time; a game that makes few frames still delivers ~1.
		const media = window.length >= 2 ? (window.at(-1)!.ptsMs - window[0].ptsMs) / this.params.fpsWindowMs : 0;
		if (window.length >= 2 && media > 0.75) return undefined;
		this.#fpsReportedAt = now;
		return `delivered ${fps.toFixed(0)} fps of ${rate}`;
	}
}
