// Node check of how far the sound waits for the picture (run by
// tests/test_video_follow.py: bundled with esbuild, run in node). Prints
// {"failures": [...], "figures": {...}} as JSON.
//
// Page time in ms; offsets are page time minus pts. The sound could be heard at
// EARLIEST; frames are shown at a 60 Hz refresh (catching up) or every 33 ms (live),
// and the target is asked for every 10 ms, as each decoded audio chunk asks for it.
import { MAX_HOLD_MS, SETTLE_MS, VIDEO_WINDOW, VideoFollow } from "../src/video_follow";

const failures: string[] = [];
const figures: Record<string, number> = {};
const check = (name: string, ok: boolean, detail: unknown = ""): void => {
	if (!ok) failures.push(`${name}: ${JSON.stringify(detail)}`);
};

const EARLIEST = -1000;
const LIVE = EARLIEST + 30; // the live picture: 30 ms later than the sound could play

/** Frames shown: (page time, offset). */
type Shown = [number, number][];

/** A viewer that joined: the relay's cached group (``behindMs`` old) shown one frame
 * a refresh, each ``stepMs`` less late than the one before, then live frames. */
function join(behindMs: number, stepMs: number, seconds: number): Shown {
	const shown: Shown = [];
	let t = 0;
	for (let late = behindMs; late > LIVE - EARLIEST; late -= stepMs, t += 1000 / 60) shown.push([t, EARLIEST + late]);
	for (; t < seconds * 1000; t += 1000 / 30) shown.push([t, LIVE]);
	return shown;
}

/** The targets every 10 ms over ``shown``; what each later move costs in silence (the
 * sum of the moves later, after the first target) and the last target. */
function play(follow: VideoFollow, shown: Shown): { silenceMs: number; last: number; targets: number[] } {
	const end = shown.at(-1)![0];
	const targets: number[] = [];
	let next = 0;
	for (let now = 0; now <= end; now += 10) {
		while (next < shown.length && shown[next][0] <= now) follow.presented(shown[next++][1]);
		targets.push(follow.target(EARLIEST, now));
	}
	let silenceMs = 0;
	for (let i = 1; i < targets.length; i++) silenceMs += Math.max(0, targets[i] - targets[i - 1]);
	return { silenceMs, last: targets.at(-1)!, targets };
}

// A join that catches up 3 s of video, each frame shown 120, 40 or 15 ms less late than
// the one before: the old rule (follow at once) moved the target up to MAX_HOLD_MS
// later as the catch-up frames came within it; now one move, to the live picture.
for (const [name, step] of [
	["fast page", 120],
	["slow page", 40],
	["slower page", 15],
] as const) {
	const shown = join(3000, step, 7);
	const before = play(new VideoFollow(0), shown);
	const now = play(new VideoFollow(), shown);
	figures[`${name}: silence before (ms)`] = before.silenceMs;
	figures[`${name}: silence now (ms)`] = now.silenceMs;
	check(`${name}: one move, to the live picture`, now.silenceMs <= LIVE - EARLIEST, now.silenceMs);
	check(`${name}: it follows the live picture`, now.last === LIVE, now.last);
	check(`${name}: follows as before once settled`, before.last === LIVE, before.last);
}
check("the old rule moved later than the live picture on a slow page", figures["slow page: silence before (ms)"] > 2 * (LIVE - EARLIEST), figures);

// A picture steadily 30 ms late: followed once it has been within the hold SETTLE_MS.
{
	const follow = new VideoFollow();
	for (let i = 0; i < VIDEO_WINDOW; i++) follow.presented(LIVE);
	check("not yet", follow.target(EARLIEST, 0) === EARLIEST);
	check("still settling", follow.target(EARLIEST, SETTLE_MS - 10) === EARLIEST);
	check("settled: follows", follow.target(EARLIEST, SETTLE_MS) === LIVE);
	// Earlier than the sound could play: the sound plays as early as it can.
	for (let i = 0; i < VIDEO_WINDOW; i++) follow.presented(EARLIEST - 50);
	check("an early picture does not pull the sound earlier", follow.target(EARLIEST, SETTLE_MS + 10) === EARLIEST);
	// Catching up (beyond the hold): not waited for, and the settling starts over.
	for (let i = 0; i < VIDEO_WINDOW; i++) follow.presented(EARLIEST + MAX_HOLD_MS + 1);
	check("catching up: not waited for", follow.target(EARLIEST, SETTLE_MS + 20) === EARLIEST);
	for (let i = 0; i < VIDEO_WINDOW; i++) follow.presented(LIVE);
	check("settles again", follow.target(EARLIEST, SETTLE_MS + 30) === EARLIEST);
	check("then follows", follow.target(EARLIEST, 2 * SETTLE_MS + 30) === LIVE);
	follow.clear();
	check("cleared: no picture", follow.videoMs === undefined && follow.target(EARLIEST, 9999) === EARLIEST);
}

console.log(JSON.stringify({ failures, figures }));
