// The AudioWorklet processor, as source text: loaded from a Blob URL so the bundle
// stays one file per page (an AudioWorklet module must be its own script).
//
// Why the position is computed, not counted: the sample played at context frame F is
// the one whose media time is F - offset (in sample frames). Playback is tied to the
// audio hardware clock plus one offset the page sets, so it cannot drift from the
// media clock however long it runs; a missing chunk (loss, a paused source) plays as
// silence for exactly its duration and the stream is back in place after it.
// Why the ramps: any jump (a gap, a new offset, a chunk arriving late) is faded out and
// in over RAMP frames (2.7 ms) instead of cut, so loss makes no click storm.
export const WORKLET_NAME = "upcast-audio";

export const WORKLET_SOURCE = `
const RAMP = 128;
const KEEP_FRAMES = sampleRate * 2; // at most 2 s queued: a stalled clock cannot grow memory
class UpcastAudio extends AudioWorkletProcessor {
	constructor() {
		super();
		this.chunks = []; // {start (media frames), data Float32Array}, sorted by start
		this.offset = null; // context frame - media frame; null until the page sets it
		this.pendingOffset = null;
		this.gain = 0;
		this.underrun = 0; // output frames played as silence while chunks were expected
		this.played = []; // media starts of chunks that began playing, with their context frame
		this.lastReport = 0;
		this.port.onmessage = (event) => {
			const m = event.data;
			if (m.type === "chunk") this.push(m.start, m.data);
			else if (m.type === "offset") this.pendingOffset = m.offset;
			else if (m.type === "reset") { this.chunks = []; }
		};
	}
	push(start, data) {
		let i = this.chunks.length;
		while (i > 0 && this.chunks[i - 1].start > start) i--;
		if (i > 0 && this.chunks[i - 1].start === start) return; // a duplicate
		this.chunks.splice(i, 0, { start, data, started: false });
		let total = 0;
		for (const c of this.chunks) total += c.data.length;
		while (total > KEEP_FRAMES && this.chunks.length > 1) total -= this.chunks.shift().data.length;
	}
	sampleAt(media) {
		// chunks are few (tens): a linear scan from the front is cheap and simple.
		for (const c of this.chunks) {
			if (media < c.start) return null;
			const i = media - c.start;
			if (i < c.data.length) {
				if (!c.started) { c.started = true; this.played.push([c.start, currentFrame]); }
				return c.data[i];
			}
		}
		return null;
	}
	process(inputs, outputs) {
		const out = outputs[0][0];
		const n = out.length;
		if (this.pendingOffset !== null) {
			if (this.offset === null || this.gain === 0) { this.offset = this.pendingOffset; this.pendingOffset = null; }
		}
		if (this.offset === null) { out.fill(0); return true; }
		const jumping = this.pendingOffset !== null; // fade out first, then move
		let silent = 0;
		for (let k = 0; k < n; k++) {
			const media = currentFrame + k - this.offset;
			const s = jumping ? null : this.sampleAt(media);
			const target = s === null ? 0 : 1;
			if (this.gain < target) this.gain = Math.min(target, this.gain + 1 / RAMP);
			else if (this.gain > target) this.gain = Math.max(target, this.gain - 1 / RAMP);
			if (s === null) { silent++; out[k] = this.gain * (this.last ?? 0); this.last = (this.last ?? 0) * 0.98; }
			else { out[k] = this.gain * s; this.last = s; }
		}
		if (jumping && this.gain === 0) { this.offset = this.pendingOffset; this.pendingOffset = null; }
		// Forget what has been played.
		const now = currentFrame + n - this.offset;
		while (this.chunks.length && this.chunks[0].start + this.chunks[0].data.length <= now) this.chunks.shift();
		if (silent && this.chunks.length) this.underrun += silent;
		for (let ch = 1; ch < outputs[0].length; ch++) outputs[0][ch].set(out);
		if (currentFrame - this.lastReport >= sampleRate / 20) {
			this.lastReport = currentFrame;
			let buffered = 0;
			for (const c of this.chunks) buffered += c.data.length;
			this.port.postMessage({ type: "report", frame: currentFrame, offset: this.offset, buffered, underrun: this.underrun, played: this.played });
			this.played = [];
		}
		return true;
	}
}
registerProcessor("${WORKLET_NAME}", UpcastAudio);
`;
