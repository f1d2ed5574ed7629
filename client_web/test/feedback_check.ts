// Node check of the player's receive counters, feedback message and keyframe recovery
// (run by tests/e2e/test_player_feedback_e2e.py: bundled with esbuild, run in node).
// argv: fragment files written by server/media/cmaf.py media_fragment, as
// "<path>:<sequence>:<decode_time>". Prints {"failures": [...]} as JSON.
import { readFileSync } from "node:fs";
import { FREEZE_MS, LATE_MS, MAX_FEEDBACK_FRAMES, ReceiveStats } from "../src/feedback";
import { readFragmentHeader } from "../src/fragment";
import { KeyframeRecovery, REQUEST_INTERVAL_MS, RETRY_MS } from "../src/recovery";

const failures: string[] = [];
const check = (name: string, ok: boolean, detail: unknown = ""): void => {
	if (!ok) failures.push(`${name}: ${JSON.stringify(detail)}`);
};

// mfhd and tfdt of the server's own fragments.
for (const arg of process.argv.slice(2)) {
	const [path, sequence, decodeTime] = arg.split(":");
	const header = readFragmentHeader(new Uint8Array(readFileSync(path)));
	check(`header ${path}`, header?.sequence === Number(sequence) && header?.decodeTime === Number(decodeTime), header);
}
check("not a fragment", readFragmentHeader(new Uint8Array([0, 0, 0, 8, 102, 114, 101, 101])) === undefined);

// Lost frames are jumps in mfhd; a restart of the numbering loses nothing.
const stats = new ReceiveStats();
check("first", stats.fragment(10, 1000, 100, 0) === 0);
check("next", stats.fragment(11, 2000, 100, 1) === 0);
check("jump of 3", stats.fragment(15, 6000, 100, 2) === 3);
check("new encoder from 1", stats.fragment(1, 7000, 100, 3) === 0);
check("lost total", stats.lost === 3, stats.lost);
check("bytes", stats.bytes === 400, stats.bytes);
stats.restart();
check("after restart", stats.fragment(90, 8000, 100, 4) === 0 && stats.lost === 3);

// Freezes: gaps over FREEZE_MS between shown frames; late: shown LATE_MS after arrival.
const shown = new ReceiveStats();
shown.fragment(1, 1, 10, 0);
shown.shown(1, 5);
shown.fragment(2, 2, 10, 10);
shown.shown(2, 10 + LATE_MS + 1); // late
shown.fragment(3, 3, 10, 400);
shown.shown(3, 410); // 410 - 111 = 299 ms since the last shown frame: a freeze
check("late", shown.shownLate === 1, shown.shownLate);
check("freeze", shown.freezes === 1 && Math.abs(shown.freezeMs - (410 - 10 - LATE_MS - 1)) < 1e-9, [shown.freezes, shown.freezeMs]);
check("FREEZE_MS", FREEZE_MS === 200);
shown.restart();
shown.shown(4, 5000); // across a resubscription: not a freeze
check("no freeze across restart", shown.freezes === 1);

// The report: at most 64 frames (the newest), counters cumulative, under 2048 bytes
// with the publisher's seq and sent_ms even with the largest numbers.
const big = new ReceiveStats();
for (let i = 1; i <= 100; i++) big.fragment(i, 9_007_199_254_000 + i, 1e9, 123_456_789.123456 + i);
big.groupsSkipped(2);
const body = big.report(true, 5);
check("64 frames", body.frames.length === MAX_FEEDBACK_FRAMES, body.frames.length);
check("newest kept", body.frames.at(-1)?.[0] === 9_007_199_254_100, body.frames.at(-1));
check("arrival rounded", body.frames[0][1] === Math.round((123_456_789.123456 + 37) * 10) / 10, body.frames[0]);
check("counters", body.type === "feedback" && body.player && body.skipped === 2 && body.late === 5 && body.bytes === 1e11, body);
const wire = JSON.stringify({ ...body, seq: 9_007_199_254_740_991, sent_ms: 99_999_999_999_999.9 });
check("size", new TextEncoder().encode(wire).length < 2048, wire.length);
check("frames taken", big.report(true, 5).frames.length === 0);

// Recovery: ask at once, at most one per REQUEST_INTERVAL_MS, retry after RETRY_MS.
const r = new KeyframeRecovery();
check("idle", !r.poll(0) && r.wakeIn(0) === undefined);
r.need(1000, "lost");
check("asks at once", r.poll(1000) && r.requests === 1);
check("not twice", !r.poll(1001));
r.need(1100, "lost again"); // already waiting: nothing new
check("retry scheduled", r.wakeIn(1100) === RETRY_MS - 100, r.wakeIn(1100));
check("retries", !r.poll(1999) && r.poll(2000) && r.requests === 2);
r.keyframe(2300);
check("recovered", !r.waiting && r.recoveries === 1 && r.lastRecoveryMs === 1300 && r.wakeIn(2300) === undefined);
r.need(2400, "skip"); // 400 ms after the last request: waits for the interval
check("rate limit", !r.poll(2400) && r.wakeIn(2400) === REQUEST_INTERVAL_MS - 400 && r.poll(2500), r.wakeIn(2400));
r.keyframe(2600);
r.keyframe(2700); // a keyframe with no wait: nothing
check("one recovery per wait", r.recoveries === 2 && r.lastRecoveryMs === 200);
r.need(5000, "x");
r.reset();
check("reset", !r.waiting && !r.poll(6000) && r.requests === 3);

console.log(JSON.stringify({ failures }));
