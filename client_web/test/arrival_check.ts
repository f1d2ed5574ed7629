// Node check of the sound's arrival bound (run by tests/test_arrival_bound.py: bundled
// with esbuild, run in node). Prints {"failures": [...], "bounds": {...}} as JSON.
import { ArrivalBound, LATE_MS, MAX_STALL_CHUNKS, MERGE_CHUNKS } from "../src/arrival_bound";
import { Window } from "../src/stats";

const failures: string[] = [];
const bounds: Record<string, number | undefined> = {};
const check = (name: string, ok: boolean, detail: unknown = ""): void => {
	if (!ok) failures.push(`${name}: ${JSON.stringify(detail)}`);
};

// A quiet page: arrival offsets -1000 +- 5 ms (a fixed pseudo-random sequence).
let seed = 7;
const jitter = (): number => {
	seed = (seed * 1103515245 + 12345) % 2147483648;
	return (seed / 2147483648) * 10 - 5;
};
const BASE = -1000;
const CAPACITY = 300;

// A stall of the page of ``ms``: the chunks due meanwhile all come out at its end, the
// first ``ms`` late, each next one a chunk (10 ms) less.
const stall = (ms: number): number[] => Array.from({ length: Math.floor(ms / 10) }, (_, k) => BASE + ms - 10 * k);

function run(name: string, offsets: number[]): number | undefined {
	const bound = new ArrivalBound(CAPACITY);
	const plain = new Window(CAPACITY);
	for (const v of offsets) {
		bound.push(v);
		plain.push(v);
	}
	bounds[name] = bound.bound();
	bounds[`${name} (p95)`] = plain.percentile(95);
	return bound.bound();
}

const quiet = (n: number): number[] => Array.from({ length: n }, () => BASE + jitter());

check("empty", new ArrivalBound(CAPACITY).bound() === undefined);
const nan = new ArrivalBound(CAPACITY);
nan.push(Number.NaN);
nan.push(Number.POSITIVE_INFINITY);
check("not finite is ignored", nan.count === 0, nan.count);

// Quiet: the 95th percentile, as before.
const q = run("quiet", quiet(300))!;
check("quiet is the p95", q === bounds["quiet (p95)"], bounds);
check("quiet within the jitter", q > BASE && q <= BASE + 5, q);

// One 220 ms stall: ignored (its chunks missed their slots already).
const one = run("one stall", [...quiet(150), ...stall(220), ...quiet(128)])!;
check("one stall is ignored", one <= BASE + 5, one);
check("one stall moved the plain p95", bounds["one stall (p95)"]! > BASE + 50, bounds);

// A 220 ms stall and an 80 ms one, 1.5 s apart: as far as the smaller.
const two = run("two stalls", [...quiet(20), ...stall(220), ...quiet(150), ...stall(80), ...quiet(100)])!;
check("two stalls: the smaller one", two >= BASE + 70 && two <= BASE + 80, two);

// Retransmissions: a chunk 60 ms late every 0.6 s (many bursts): as before.
const retransmit = run("retransmissions", quiet(300).map((v, i) => (i % (MERGE_CHUNKS + 10) === 5 ? v + 60 : v)))!;
check("retransmissions: the plain p95", retransmit === bounds["retransmissions (p95)"], bounds);

// The same two stalls 0.3 s apart are one hiccup: ignored.
const close = run("two close stalls", [...quiet(150), ...stall(220), ...quiet(30), ...stall(80), ...quiet(90)])!;
check("two close stalls are one", close <= BASE + 5, close);

// Two equal stalls: as before (the 95th percentile lets 5 % of the chunks miss).
const equal = run("two equal stalls", [...quiet(40), ...stall(120), ...quiet(150), ...stall(120), ...quiet(86)])!;
check("two equal stalls: the plain p95", equal === bounds["two equal stalls (p95)"] && equal > BASE + 40, bounds);

// A lossy path: every 10th chunk 20 ms late (one long burst): the 95th percentile of
// all chunks, as before.
const lossy = run("lossy", quiet(300).map((v, i) => (i % 10 === 9 ? v + 20 : v)))!;
check("lossy is the plain p95", lossy === bounds["lossy (p95)"], bounds);
check("lossy covers the late tenth", lossy >= BASE + 15, lossy);

// Late by less than LATE_MS is jitter, not a burst: the plain p95.
const mild = run("mild", quiet(300).map((v, i) => (i % 10 === 0 ? v + LATE_MS - 6 : v)))!;
check("mild is the plain p95", mild === bounds["mild (p95)"], bounds);

// A loaded page: every 7th chunk 25 ms late, and one 360 ms stall: the stall counts
// once, the jitter as before.
const loadedOnly = run("loaded", quiet(300).map((v, i) => (i % 7 === 3 ? v + 25 : v)))!;
const loadedStall = quiet(300).map((v, i) => (i % 7 === 3 ? v + 25 : v));
loadedStall.splice(150, 36, ...stall(360));
const loaded = run("loaded, one stall", loadedStall)!;
check("loaded: jitter covered", loadedOnly >= BASE + 15, loadedOnly);
check("loaded: the stall counts once", Math.abs(loaded - loadedOnly) <= 5, bounds);
check("loaded: the stall moved the plain p95", bounds["loaded, one stall (p95)"]! > BASE + 100, bounds);

// A step in the path's delay (the last 0.8 s all 100 ms later) is not a stall.
const step = run("delay step", [...quiet(220), ...quiet(80).map((v) => v + 100)])!;
check("a delay step counts", step >= BASE + 90 && MAX_STALL_CHUNKS < 80, step);

// The window forgets: once the bursts age out, the bound is back to the quiet one.
const aged = run("aged out", [...stall(220), ...quiet(50), ...stall(220), ...quiet(300)])!;
check("aged out", aged <= BASE + 5, aged);

console.log(JSON.stringify({ failures, bounds }));
