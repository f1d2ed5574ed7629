// Node check of the spectator's rendition choice (client_web/src/abr.ts), run by
// tests/test_web_abr.py: bundled with esbuild, run in node. Prints
// {"failures": [...], "figures": {...}} as JSON.
//
// Two kinds of checks: the rules one at a time, fed by hand; and whole runs over a
// simulated link (a FIFO bottleneck with a rate, an RTT and packet loss between the
// relay and the page, the relay replaying a track's latest group to a new
// subscription and resetting a group that waits past its latency bound), with the
// page's switching as media.ts does it (subscribe, move over at the first frame).
import { Abr, type AbrDecision, DEFAULT_PARAMS, renditionParams, type Rung, spectatorLadder } from "../src/abr";
import { KeyframeRecovery, LISTEN_WAIT_MS, REFETCH_RETRY_MS } from "../src/recovery";

const failures: string[] = [];
const figures: Record<string, unknown> = {};
const check = (name: string, ok: boolean, detail: unknown = ""): void => {
	if (!ok) failures.push(`${name}: ${JSON.stringify(detail)}`);
};

// The catalog of a 1280x720 display at 30 fps: the player's track, then two rungs.
const CATALOG = [
	{ track: "video", codedWidth: 1280, codedHeight: 720, framerate: 30, bitrate: 3_000_000 },
	{ track: "video.640x360", codedWidth: 640, codedHeight: 360, framerate: 30, bitrate: 750_000 },
	{ track: "video.320x180", codedWidth: 320, codedHeight: 180, framerate: 30, bitrate: 190_000 },
];
const LADDER: Rung[] = spectatorLadder(CATALOG);
const LOW = "video.320x180";
const HIGH = "video.640x360";
const FRAME_MS = 1000 / 30;

// ---- the ladder and the URL

check("ladder: rungs only, cheapest first", LADDER.map((r) => r.track).join() === `${LOW},${HIGH}`, LADDER);
const single = spectatorLadder([CATALOG[0]]);
check("ladder: no rung, the first alone", single.length === 1 && single[0].track === "video", single);
const priced = spectatorLadder([CATALOG[0], { track: "video.640x360", codedWidth: 640, codedHeight: 360, framerate: 30 }]);
check("ladder: a rung without a bitrate is priced by its pixels", priced[0].bitrate > 500_000 && priced[0].bitrate < 1_000_000, priced);
check("params: ?rendition=", renditionParams("?rendition=video.320x180").forced === LOW);
check("params: ?abr=off", renditionParams("?abr=off").abrOff && !renditionParams("?abr=on").abrOff && renditionParams("").forced === undefined);

// ---- helpers for hand-fed runs

/** Frames of the playing track at 30 fps from `t0` for `ms`, one-way delay `owd(i)`;
 * a keyframe of `keyBytes` every 30 frames arriving `keyExtraMs` later. Returns the
 * first decision (and when), stopping there unless `all`. */
function feed(
	abr: Abr,
	t0: number,
	ms: number,
	options: { owd?: (i: number) => number; bytes?: number; keyBytes?: number; keyExtraMs?: number; poll?: boolean; all?: boolean } = {},
): { decision?: AbrDecision; at?: number; decisions: AbrDecision[]; end: number } {
	const owd = options.owd ?? (() => 40);
	const decisions: AbrDecision[] = [];
	let first: { decision?: AbrDecision; at?: number } = {};
	const n = Math.floor(ms / FRAME_MS);
	for (let i = 0; i < n; i++) {
		const pts = t0 + i * FRAME_MS;
		const key = i % 30 === 0;
		const arrival = pts + owd(i) + (key ? (options.keyExtraMs ?? 4) : 0);
		const got = [
			abr.frame(arrival, key ? (options.keyBytes ?? 15_000) : (options.bytes ?? 700), pts * 1000, key),
			options.poll === false ? undefined : abr.poll(arrival + 1),
		];
		for (const d of got) {
			if (!d) continue;
			decisions.push(d);
			if (!first.decision) first = { decision: d, at: arrival };
		}
		if (first.decision && !options.all) break;
	}
	return { ...first, decisions, end: t0 + n * FRAME_MS };
}

/** An ABR started on `track` (switched there at `t`). */
function on(track: string, t = 0, params = {}): Abr {
	const abr = new Abr(params);
	abr.setLadder(LADDER, t);
	if (track !== abr.playing) {
		abr.switched(t, track);
	}
	return abr;
}

// ---- start

{
	const abr = new Abr();
	check("start: the lowest rung (190 kbit/s under the 500 kbit/s budget)", abr.setLadder(LADDER, 0) === LOW, abr.playing);
	check("start: reason", /start/.test(abr.reason ?? ""), abr.reason);
	const rich = new Abr({ startBudgetBps: 1_000_000 });
	check("start: the highest rung under the budget", rich.setLadder(LADDER, 0) === HIGH, rich.playing);
	const poor = new Abr({ startBudgetBps: 100_000 });
	check("start: the lowest when none fits", poor.setLadder(LADDER, 0) === LOW, poor.playing);
	check("start: the same catalog again keeps it", abr.setLadder(LADDER, 5) === LOW && abr.switches === 0);
}

// ---- down at once on a skipped group

{
	const abr = on(HIGH);
	feed(abr, 0, 2000, { all: true });
	const d = abr.skipped(2100, "group reset");
	check("skip: down at once, one rung", d?.direction === "down" && d.track === LOW, d);
	check("skip: a second skip while the lower rung comes changes nothing", abr.skipped(2110) === undefined);
	abr.switched(2200, LOW);
	check("skip: on the lowest rung nothing lower", abr.skipped(2300) === undefined && abr.playing === LOW);
	check("skip: switches counted", abr.switches === 2, abr.switches); // the test's start move + the down
}

// ---- down on a growing delay, not on jitter or keyframe spikes

{
	const steady = on(HIGH);
	let seed = 3;
	const jitter = (): number => {
		seed = (seed * 1103515245 + 12345) % 2147483648;
		return (seed / 2147483648) * 30; // 0-30 ms
	};
	const calm = feed(steady, 0, 20_000, { owd: () => 40 + jitter(), keyExtraMs: 60, poll: true, all: true });
	check("delay: jitter and keyframe spikes are not a queue", calm.decisions.every((d) => d.direction !== "down"), calm.decisions);

	const growing = on(HIGH);
	feed(growing, 0, 3000, { all: true });
	// From 3 s on, each frame 8 ms later than the one before (a link at ~80 % of the rung).
	const grow = feed(growing, 3000, 5000, { owd: (i) => 40 + 8 * i });
	check("delay: growing delay goes down", grow.decision?.direction === "down" && grow.decision.track === LOW, grow);
	check("delay: within a second", grow.at !== undefined && grow.at - 3000 < 1200, grow.at);
	check("delay: says why", /delay growing/.test(grow.decision?.reason ?? ""), grow.decision?.reason);
	figures.delay_down_after_ms = grow.at === undefined ? null : Math.round(grow.at - 3000);
}

// ---- down on delivered fps clearly under the rung's (the link), not on a slow game

{
	const slowLink = on(HIGH);
	// 10 fps arriving, the frames made 33 ms apart: they arrive slower than made.
	let t = 0;
	let got: AbrDecision | undefined;
	for (let i = 0; i < 60 && !got; i++) {
		t = i * 100;
		got = slowLink.frame(t, 700, i * FRAME_MS * 1000) ?? slowLink.poll(t + 1);
	}
	check("fps: frames arriving slower than made go down", got?.direction === "down" && /fps|delay/.test(got.reason), got);
	const slowGame = on(HIGH);
	let none = true;
	for (let i = 0; i < 80; i++) {
		t = i * 100; // the game makes 10 fps and they arrive as made
		if (slowGame.frame(t + 40, 700, t * 1000) ?? slowGame.poll(t + 41)) none = false;
	}
	check("fps: a game making 10 fps is not a slow link", none);
}

// ---- up after a hold with headroom; not without headroom

{
	const abr = on(LOW);
	// Keyframes of 15 kB arriving 4 ms over the floor: ~30 Mbit/s of headroom.
	const run = feed(abr, 0, 20_000);
	check("up: after the hold", run.decision?.direction === "up" && run.decision.track === HIGH, run);
	check("up: not before the hold", run.at !== undefined && run.at >= DEFAULT_PARAMS.upHoldMs, run.at);
	check("up: soon after it", run.at !== undefined && run.at < DEFAULT_PARAMS.upHoldMs + 1500, run.at);
	check("up: says why", /throughput/.test(run.decision?.reason ?? ""), run.decision?.reason);
	figures.up_after_ms = run.at === undefined ? null : Math.round(run.at);
	const tight = on(LOW);
	// The same keyframes 100 ms late: 1.2 Mbit/s, under 2 x 750 kbit/s.
	const stay = feed(tight, 0, 30_000, { keyExtraMs: 100, all: true });
	check("up: not without headroom", stay.decisions.length === 0, stay.decisions);
	const noisy = on(LOW);
	// Headroom but a skip every 3 s: never stable for the hold.
	let ups = 0;
	for (let s = 0; s < 10; s++) {
		const r = feed(noisy, s * 3000, 3000, { all: true });
		ups += r.decisions.filter((d) => d.direction === "up").length;
		noisy.skipped(s * 3000 + 2990);
	}
	check("up: never without a stable hold", ups === 0, ups);
	// Nothing measured (keyframes no bigger than the other frames, no burst): the up-switch
	// is the probe, after the same hold.
	const blind = on(LOW);
	const probe = feed(blind, 0, 20_000, { keyBytes: 700 });
	check("up: a probe when nothing is measured", probe.decision?.direction === "up" && /probing/.test(probe.decision.reason), probe);
	check("up: the probe waits the hold", (probe.at ?? 0) >= DEFAULT_PARAMS.upHoldMs, probe.at);
	// A rung left for trouble is not probed blindly again soon; with evidence it is.
	const left = on(HIGH);
	feed(left, 0, 2000, { keyBytes: 700, all: true });
	left.skipped(2100, "group reset");
	left.switched(2200, LOW);
	const quiet = feed(left, 2200, 60_000, { keyBytes: 700, all: true });
	check("up: no blind probe back to a rung just left", quiet.decisions.length === 0, quiet.decisions);
	const evidence = feed(left, 62_200, 10_000);
	check("up: evidence brings it back", evidence.decision?.direction === "up" && /throughput/.test(evidence.decision.reason), evidence);
	// A backlog (frames arriving slower than made) measures the link: 700 B every 70 ms.
	const backlog = on(LOW);
	feed(backlog, 0, 3000, { keyBytes: 700, all: true });
	for (let i = 0; i < 40; i++) backlog.frame(3000 + 40 + 70 * i, 700, (3000 + i * FRAME_MS) * 1000);
	const measured = backlog.estimate(6000);
	check("up: a backlog is a sample of the link", measured !== undefined && Math.abs(measured - 80_000) < 10_000, measured);
}

// ---- backoff: an up-switch that failed soon doubles the hold, bounded

{
	const abr = on(LOW);
	const holds: number[] = [];
	const upsAt: number[] = [];
	let t = 0;
	for (let round = 0; round < 6; round++) {
		const run = feed(abr, t, 120_000);
		if (run.decision?.direction !== "up" || run.at === undefined) break;
		upsAt.push(run.at);
		abr.switched(run.at + 100, HIGH);
		feed(abr, run.at + 100, 2000, { all: true });
		const down = abr.skipped(run.at + 2100, "group reset");
		check(`backoff ${round}: down after the failed up`, down?.track === LOW, down);
		abr.switched(run.at + 2200, LOW);
		holds.push(abr.holdMs);
		t = run.at + 2200;
	}
	check("backoff: the hold doubles", holds[0] === 2 * DEFAULT_PARAMS.upHoldMs && holds[1] === 4 * DEFAULT_PARAMS.upHoldMs, holds);
	check("backoff: bounded", Math.max(...holds) <= DEFAULT_PARAMS.maxUpHoldMs && holds.at(-1) === DEFAULT_PARAMS.maxUpHoldMs, holds);
	const gaps = upsAt.slice(1).map((at, i) => at - upsAt[i]);
	check("backoff: ups further apart", gaps.every((g, i) => i === 0 || g >= gaps[i - 1] - 1) && gaps[1] > 2 * gaps[0] - 3000, gaps);
	check("backoff: counted", abr.failedUps === holds.length, abr.failedUps);
	figures.backoff_holds_ms = holds;
	// A rung that holds for the fail window halves the hold (down to the base).
	const before = abr.holdMs;
	abr.switched(t + 100, HIGH); // an up that works this time
	feed(abr, t + 100, DEFAULT_PARAMS.failWindowMs + 500, { all: true });
	check("backoff: a rung that held halves the hold", abr.holdMs === before / 2, [before, abr.holdMs]);
}

// ---- a pending switch: timeout, failure, trouble while probing up

{
	const abr = on(LOW);
	const up = feed(abr, 0, 20_000);
	check("pending: up asked", abr.pending === HIGH, abr.pending);
	let back: AbrDecision | undefined;
	for (let t = (up.at ?? 0) + 100; t < (up.at ?? 0) + 5000 && !back; t += 250) back = abr.poll(t);
	check("pending: given up after the timeout", back?.direction === "back" && back.track === LOW && abr.pending === undefined, back);
	check("pending: a probe that never came counts as failed", abr.holdMs === 2 * DEFAULT_PARAMS.upHoldMs, abr.holdMs);
	const refused = on(LOW);
	feed(refused, 0, 20_000);
	refused.switchFailed(20_000, HIGH, "not found");
	check("pending: a refused switch stays", refused.pending === undefined && refused.target === LOW && refused.failedUps === 1);
	const probing = on(LOW);
	feed(probing, 0, 20_000);
	const stay = probing.skipped(20_100);
	check("pending: trouble while probing up cancels it", stay?.direction === "back" && stay.track === LOW && probing.pending === undefined, stay);
}

// ---- one rendition: never switches

{
	const abr = new Abr();
	check("single: plays it", abr.setLadder(single, 0) === "video");
	const decisions: (AbrDecision | undefined)[] = [];
	decisions.push(...feed(abr, 0, 10_000, { all: true }).decisions);
	decisions.push(abr.skipped(10_100), abr.late(10_200, 0), abr.late(10_300, 50));
	decisions.push(...feed(abr, 10_400, 5000, { owd: (i) => 40 + 10 * i, all: true }).decisions);
	for (let t = 16_000; t < 30_000; t += 250) decisions.push(abr.poll(t)); // a stall
	check("single: never a decision", decisions.every((d) => d === undefined), decisions.filter(Boolean));
	check("single: no switch", abr.switches === 0 && abr.playing === "video");
}

// ---- the decoder falling behind

{
	const abr = on(HIGH);
	abr.late(100, 0);
	check("late: a frame or two is not a reason", abr.late(200, 2) === undefined);
	const d = abr.late(300, 9);
	check("late: a decoder behind goes down", d?.direction === "down" && /decoder/.test(d.reason), d);
}

// ---- a stall

{
	const abr = on(HIGH);
	feed(abr, 0, 2000, { all: true });
	let d: AbrDecision | undefined;
	for (let t = 2100; t < 6000 && !d; t += 250) d = abr.poll(t);
	check("stall: no frame for a while goes down", d?.direction === "down" && /no frame|fps/.test(d.reason), d);
	// Without a frame rate in the catalog only the stall rule sees it.
	const bare = new Abr();
	bare.setLadder(LADDER.map((r) => ({ ...r, framerate: undefined })), 0);
	bare.switched(0, HIGH);
	feed(bare, 0, 2000, { all: true });
	let e: AbrDecision | undefined;
	let at = 0;
	for (at = 2100; at < 6000 && !e; at += 250) e = bare.poll(at);
	check("stall: the stall rule", e?.direction === "down" && /no frame/.test(e.reason) && at - 2000 <= DEFAULT_PARAMS.stallMs + 600, [e, at]);
}

// ---- garbage in

{
	const abr = new Abr({ upHoldMs: Number.NaN, queueDownMs: -5 } as never);
	check("garbage: bad params fall back", abr.params.upHoldMs === DEFAULT_PARAMS.upHoldMs && abr.params.queueDownMs === DEFAULT_PARAMS.queueDownMs, abr.params);
	check("garbage: nothing before a ladder", abr.frame(1, 100, 1000) === undefined && abr.poll(5) === undefined && abr.skipped(6) === undefined);
	abr.setLadder([...LADDER, { track: "x", bitrate: Number.NaN } as Rung, { track: 7, bitrate: 1 } as unknown as Rung], 0);
	check("garbage: bad rungs dropped", abr.ladder.length === 2, abr.ladder);
	on(LOW); // a fresh one below
	const g = on(HIGH);
	const junk: unknown[] = [Number.NaN, Number.POSITIVE_INFINITY, Number.NEGATIVE_INFINITY, undefined, null, "12", {}];
	let decided = false;
	for (const x of junk) {
		for (const d of [
			g.frame(x as number, 100, 1000),
			g.frame(10, x as number, 1000),
			g.frame(10, 100, x as number),
			g.frame(10, -5, 1000),
			g.skipped(x as number),
			g.late(x as number, 5),
			g.late(20, x as number),
			g.poll(x as number),
		]) {
			if (d) decided = true;
		}
		g.switched(x as number, LOW);
		g.switchFailed(x as number, HIGH, "x");
	}
	check("garbage: ignored", !decided && g.playing === HIGH, g.playing);
	const after = feed(g, 0, 3000, { all: true });
	check("garbage: still works after", after.decisions.length === 0 && g.playing === HIGH, after.decisions);
	check("garbage: estimate stays finite", g.estimate(3000) === undefined || Number.isFinite(g.estimate(3000)), g.estimate(3000));
}

// ---- whole runs over a simulated link

interface Link {
	/** bit/s, or bit/s at page time t (ms). */
	rateBps: number | ((t: number) => number);
	rttMs: number;
	/** Per 1200-byte packet; a lost packet holds its frame (and those behind) one RTT. */
	loss: number;
	/** A keyframe's size over a delta frame's: ~1 for the rungs' one-frame VBV (default 1.2). */
	keyRatio?: number;
	/** Whether the relay has every rung's latest group cached (others watch them; default
	 * true); if not, a new subscription waits for a keyframe the publisher is asked for. */
	cached?: boolean;
}

interface RunResult {
	firstPictureMs?: number;
	final?: string;
	switches: { t: number; to: string; reason: string }[];
	decisions: AbrDecision[];
	seconds: Record<string, number>;
	skips: number;
}

const GOP = 30;
const RELAY_MAX_QUEUE_MS = 1000; // a viewer whose frames wait longer is skipped a group
const ENCODE_MS = 5;

/** A frame of a rung: keyframes `keyRatio` x a delta frame, averaging the cap. */
function frameBytes(rung: Rung, key: boolean, keyRatio: number): number {
	const delta = (rung.bitrate / 8 / 30) * (GOP / (GOP - 1 + keyRatio));
	return Math.round(key ? keyRatio * delta : delta);
}

function simulate(link: Link, seconds: number, seed = 1): RunResult {
	let rnd = seed;
	const random = (): number => {
		rnd = (rnd * 1103515245 + 12345) % 2147483648;
		return rnd / 2147483648;
	};
	const abr = new Abr();
	const rung = (track: string): Rung => LADDER.find((r) => r.track === track)!;
	const oneWay = link.rttMs / 2;
	// Connection, WebTransport session, catalog: three round trips before the subscribe.
	const start = 3 * link.rttMs;
	let linkFree = 0;
	type Delivery = { t: number; track: string; n: number; bytes: number; key: boolean } | { t: number; track: string; skip: true };
	const deliveries: Delivery[] = [];
	// Subscriptions at the relay: track -> from when it sends, until when, the group it skips.
	const subs = new Map<string, { from: number; until: number; skipGroup: number; sentFirst: boolean }>();
	let playing = abr.setLadder(LADDER, start)!;
	let pending: string | undefined;
	const result: RunResult = { switches: [], decisions: [], seconds: {}, skips: 0 };
	let since = start;
	const keyRatio = link.keyRatio ?? 1.2;
	// The ladder's keyframes, on the same frames on every rung: every GOP frames, or on
	// a request (a new subscription the relay cannot replay) at least 8 frames apart.
	const groupOf: number[] = [];
	let nextFrame = 0;
	let lastKey = -GOP;
	let keyWanted = false;
	const makeFrame = (n: number): void => {
		const key = n - lastKey >= GOP || (keyWanted && n - lastKey >= 8);
		if (key) {
			lastKey = n;
			keyWanted = false;
		}
		groupOf[n] = lastKey;
	};

	const send = (track: string, n: number, ready: number): void => {
		const sub = subs.get(track);
		if (!sub || ready > sub.until) return;
		const group = groupOf[n];
		if (group === sub.skipGroup) return;
		if (!sub.sentFirst && n !== group) return; // a subscription starts at a group
		const startAt = Math.max(linkFree, ready);
		if (startAt - ready > RELAY_MAX_QUEUE_MS) {
			sub.skipGroup = group; // the relay resets this group: the rest of it is not sent
			deliveries.push({ t: startAt + oneWay, track, skip: true });
			return;
		}
		sub.sentFirst = true;
		const bytes = frameBytes(rung(track), n === group, keyRatio);
		const packets = Math.ceil(bytes / 1200);
		const rate = typeof link.rateBps === "number" ? link.rateBps : link.rateBps(startAt);
		let end = startAt + (bytes * 8 * 1000) / rate;
		for (let p = 0; p < packets; p++) if (random() < link.loss) end += link.rttMs;
		linkFree = end;
		deliveries.push({ t: end + oneWay, track, n, bytes, key: n === group });
	};
	const subscribe = (track: string, at: number): void => {
		const from = at + oneWay;
		subs.set(track, { from, until: Number.POSITIVE_INFINITY, skipGroup: -1, sentFirst: false });
		// The relay replays the track's latest group (from its keyframe) at once, or asks
		// the publisher for one.
		const now = Math.min(Math.floor((from - ENCODE_MS) / FRAME_MS), nextFrame - 1);
		if (link.cached === false) keyWanted = true;
		else for (let n = groupOf[now] ?? now; n <= now && groupOf[n] !== undefined; n++) send(track, n, from);
	};
	const unsubscribe = (track: string, at: number): void => {
		const sub = subs.get(track);
		if (sub) sub.until = at + oneWay;
	};
	const apply = (d: AbrDecision | undefined, t: number): void => {
		if (!d) return;
		result.decisions.push(d);
		if (pending !== undefined) unsubscribe(pending, t);
		pending = d.track === playing ? undefined : d.track;
		if (pending) subscribe(pending, t);
	};

	while (nextFrame * FRAME_MS + ENCODE_MS <= start) makeFrame(nextFrame++);
	subscribe(playing, start);
	let nextPoll = start;
	for (let t = start; t < seconds * 1000; t += 1) {
		// The encoder: every rung makes each frame; the relay forwards it to subscribers.
		while (nextFrame * FRAME_MS + ENCODE_MS <= t) {
			makeFrame(nextFrame);
			for (const track of subs.keys()) send(track, nextFrame, nextFrame * FRAME_MS + ENCODE_MS);
			nextFrame++;
		}
		deliveries.sort((a, b) => a.t - b.t);
		while (deliveries.length > 0 && deliveries[0].t <= t) {
			const d = deliveries.shift()!;
			if ("skip" in d) {
				if (d.track === playing) {
					result.skips++;
					apply(abr.skipped(d.t, "group reset"), d.t);
				}
				continue;
			}
			if (d.track === pending) {
				// The new track's first frame: move over, drop the old one.
				result.seconds[playing] = (result.seconds[playing] ?? 0) + (d.t - since) / 1000;
				since = d.t;
				unsubscribe(playing, d.t);
				abr.switched(d.t, d.track);
				result.switches.push({ t: d.t, to: d.track, reason: abr.reason ?? "" });
				playing = d.track;
				pending = undefined;
			}
			if (d.track !== playing) continue;
			result.firstPictureMs ??= d.t;
			apply(abr.frame(d.t, d.bytes, d.n * FRAME_MS * 1000, d.key), d.t);
		}
		if (t >= nextPoll) {
			apply(abr.poll(t), t);
			nextPoll += 250;
		}
	}
	result.seconds[playing] = (result.seconds[playing] ?? 0) + (seconds * 1000 - since) / 1000;
	result.final = playing;
	for (const k of Object.keys(result.seconds)) result.seconds[k] = Math.round(result.seconds[k] * 10) / 10;
	return result;
}

{
	// 300 kbit/s, 100 ms: the 190 kbit/s rung fits, the 750 kbit/s one never does.
	const narrow = simulate({ rateBps: 300_000, rttMs: 100, loss: 0 }, 90);
	figures.link_300k = { first: Math.round(narrow.firstPictureMs ?? -1), final: narrow.final, switches: narrow.switches.length, seconds: narrow.seconds, skips: narrow.skips };
	check("300k: first picture within 1 s", (narrow.firstPictureMs ?? Infinity) < 1000, narrow.firstPictureMs);
	check("300k: ends on the lowest rung", narrow.final === LOW, narrow.final);
	check("300k: and stays (never up)", narrow.switches.length === 0 && narrow.decisions.length === 0, narrow.decisions);
	check("300k: no skipped group", narrow.skips === 0, narrow.skips);

	// The same link with 2 % loss: still the lowest, at most a probe or two.
	const lossyNarrow = simulate({ rateBps: 300_000, rttMs: 100, loss: 0.02 }, 90, 5);
	figures.link_300k_lossy = { final: lossyNarrow.final, switches: lossyNarrow.switches.length, seconds: lossyNarrow.seconds, skips: lossyNarrow.skips };
	check("300k lossy: ends on the lowest rung", lossyNarrow.final === LOW, lossyNarrow);
	check("300k lossy: (almost) all the time there", (lossyNarrow.seconds[LOW] ?? 0) > 85, lossyNarrow.seconds);

	// 4 Mbit/s, 60 ms, 1 % loss: a picture within 1 s, up to the 750 kbit/s rung, and it stays.
	const good = simulate({ rateBps: 4_000_000, rttMs: 60, loss: 0.01 }, 60, 2);
	figures.link_4m_lossy = { first: Math.round(good.firstPictureMs ?? -1), final: good.final, switches: good.switches.map((s) => [Math.round(s.t), s.to]), seconds: good.seconds, skips: good.skips };
	check("4M: first picture within 1 s", (good.firstPictureMs ?? Infinity) < 1000, good.firstPictureMs);
	check("4M: ends on the higher rung", good.final === HIGH, good);
	check("4M: one switch, within 10 s", good.switches.length === 1 && good.switches[0].t < 10_000, good.switches);

	// 4 Mbit/s that falls to 500 kbit/s at 30 s: down within about a second, and no
	// probe up while it stays there.
	const falls = simulate({ rateBps: (t) => (t < 30_000 ? 4_000_000 : 500_000), rttMs: 60, loss: 0 }, 90, 4);
	const downAt = falls.switches.find((s) => s.to === LOW && s.t > 30_000);
	figures.link_falls = { final: falls.final, switches: falls.switches.map((s) => [Math.round(s.t), s.to, s.reason]), seconds: falls.seconds, skips: falls.skips };
	check("falls: up first", falls.switches[0]?.to === HIGH && falls.switches[0].t < 10_000, falls.switches);
	check("falls: down within 1.5 s of the drop", downAt !== undefined && downAt.t < 31_500, falls.switches);
	check("falls: ends low, no further switch", falls.final === LOW && falls.switches.length === 2, falls.switches);

	// 1 Mbit/s: the 750 kbit/s rung would fit but not with twice its cap: stays low.
	const mid = simulate({ rateBps: 1_000_000, rttMs: 40, loss: 0 }, 60, 3);
	figures.link_1m = { final: mid.final, switches: mid.switches.length, seconds: mid.seconds };
	check("1M: no oscillation", mid.switches.length <= 2, mid.switches);
}

{
	// No relay cache: no join replay to measure, so one blind probe; its failure is
	// measured and keeps the page on the lowest rung.
	const uncached = simulate({ rateBps: 300_000, rttMs: 100, loss: 0, cached: false }, 90);
	figures.link_300k_uncached = { final: uncached.final, switches: uncached.switches.map((s) => [Math.round(s.t), s.to]), seconds: uncached.seconds, skips: uncached.skips };
	check("300k uncached: ends on the lowest rung", uncached.final === LOW, uncached.final);
	check("300k uncached: one probe at most, then stays", uncached.switches.filter((s) => s.to === HIGH).length <= 1 && uncached.switches.every((s) => s.t < 10_000), uncached.switches);
	// Over five minutes: probes at most every STALE_PROBE_MS, nearly all the time low.
	const long = simulate({ rateBps: 300_000, rttMs: 100, loss: 0, cached: false }, 300);
	const probes = long.switches.filter((s) => s.to === HIGH).map((s) => Math.round(s.t));
	figures.link_300k_5min = { probes, seconds: long.seconds, skips: long.skips };
	check("300k 5 min: probes spaced", probes.every((t, i) => i === 0 || t - probes[i - 1] >= DEFAULT_PARAMS.staleProbeMs), probes);
	check("300k 5 min: low", long.final === LOW && (long.seconds[LOW] ?? 0) > 295, long.seconds);
	// A link that gets better (300 kbit/s, then 4 Mbit/s at 60 s) is found.
	const better = simulate({ rateBps: (t) => (t < 60_000 ? 300_000 : 4_000_000), rttMs: 60, loss: 0 }, 240);
	figures.link_gets_better = { final: better.final, switches: better.switches.map((s) => [Math.round(s.t), s.to]) };
	check("better: found within the stale-probe time", better.final === HIGH && better.switches.some((s) => s.to === HIGH && s.t < 60_000 + DEFAULT_PARAMS.staleProbeMs + 5000), better.switches);
}

// ---- recovery without a token: no request, a refetch if no keyframe comes

{
	const r = new KeyframeRecovery({ canRequest: false });
	r.need(1000, "group reset");
	check("listen: no request at once", !r.poll(1000) && r.requests === 0 && r.action === "refetch");
	check("listen: waits for the ladder's next keyframe", r.wakeIn(1000) === LISTEN_WAIT_MS, r.wakeIn(1000));
	r.keyframe(1900);
	check("listen: a keyframe within the wait ends it", !r.waiting && r.recoveries === 1 && r.refetches === 0);
	r.need(5000, "decoder error");
	check("listen: a refetch when none came", !r.poll(5000 + LISTEN_WAIT_MS - 1) && r.poll(5000 + LISTEN_WAIT_MS) && r.refetches === 1 && r.requests === 0);
	check("listen: again later", !r.poll(5000 + LISTEN_WAIT_MS + 1) && r.wakeIn(5000 + LISTEN_WAIT_MS) === REFETCH_RETRY_MS);
	const asks = new KeyframeRecovery();
	asks.need(0, "x");
	check("with a token: asks at once", asks.poll(0) && asks.requests === 1 && asks.action === "request");
}

console.log(JSON.stringify({ failures, figures }));
