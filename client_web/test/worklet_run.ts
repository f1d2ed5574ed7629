// Runs the player's AudioWorklet processor (src/audio_worklet.ts) in node, outside any
// browser, so its gap handling can be checked sample by sample
// (tests/test_audio_concealment.py bundles and runs it).
// argv: spec.json, samples.f32 (the chunks' samples back to back), out.f32.
// spec: {sampleRate, offset, frames, lead, chunks: [[start, length], ...]} with starts
// in media frames; a chunk arrives `lead` frames before it is due (in the quantum that
// renders its slot less `lead`). Writes the `frames` output samples (context frames
// 0..frames-1) to out.f32 and prints the processor's counters as JSON.
import { readFileSync, writeFileSync } from "node:fs";
import { WORKLET_SOURCE } from "../src/audio_worklet";

interface Spec {
	sampleRate: number;
	offset: number;
	frames: number;
	lead: number;
	chunks: [number, number][];
}

const [specPath, samplesPath, outPath] = process.argv.slice(2);
const spec = JSON.parse(readFileSync(specPath, "utf8")) as Spec;
const bytes = readFileSync(samplesPath);
const samples = new Float32Array(bytes.buffer, bytes.byteOffset, bytes.byteLength / 4);

type Message = Record<string, unknown>;
const reports: Message[] = [];
let Processor: (new () => { port: { onmessage: (e: { data: Message }) => void }; process: (i: unknown, o: Float32Array[][]) => boolean }) | undefined;
const scope = globalThis as Record<string, unknown>;
scope.sampleRate = spec.sampleRate;
scope.currentFrame = 0;
scope.AudioWorkletProcessor = class {
	port = { postMessage: (m: Message) => reports.push(m), onmessage: (_e: { data: Message }) => {} };
};
scope.registerProcessor = (_name: string, cls: typeof Processor) => {
	Processor = cls;
};
new Function(WORKLET_SOURCE)();
if (!Processor) throw new Error("the worklet registered no processor");
const node = new Processor();
node.port.onmessage({ data: { type: "offset", offset: spec.offset } });
const QUANTUM = 128;
const out = new Float32Array(spec.frames);
let next = 0; // the next chunk to arrive
let at = 0; // its first sample in `samples`
for (let frame = 0; frame < spec.frames; frame += QUANTUM) {
	while (next < spec.chunks.length && spec.chunks[next][0] + spec.offset - spec.lead < frame + QUANTUM) {
		const [start, length] = spec.chunks[next++];
		node.port.onmessage({ data: { type: "chunk", start, data: samples.slice(at, at + length) } });
		at += length;
	}
	scope.currentFrame = frame;
	const block = new Float32Array(QUANTUM);
	node.process([], [[block]]);
	out.set(block.subarray(0, Math.min(QUANTUM, spec.frames - frame)), frame);
}
writeFileSync(outPath, Buffer.from(out.buffer));
const counters = node as unknown as { underrun: number; concealedTotal: number };
console.log(JSON.stringify({ underrun: counters.underrun, concealed: counters.concealedTotal, reports: reports.length }));
