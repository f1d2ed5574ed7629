// The AudioWorklet processor, as source text: loaded from a Blob URL so the bundle
// stays one file per page (an AudioWorklet module must be its own script).
//
// Why the position is computed, not counted: the sample played at context frame F is
// the one whose media time is F - offset (in sample frames). Playback is tied to the
// audio hardware clock plus one offset the page sets, so it cannot drift from the
// media clock however long it runs; a missing chunk (loss, a paused source) lasts
// exactly its duration and the stream is back in place after it.
// Why concealment: WebCodecs' Opus decoder has no packet-loss concealment (a lost
// packet is simply never decoded), and a gap played as silence, even faded, is heard
// as a crackle at a few percent loss. A gap in a playing stream is filled the way
// G.711 Appendix I and WebRTC's NetEq do: the last pitch period (2.5-15 ms, found by
// normalised autocorrelation over the last 5 ms) is repeated, at full level for 10 ms
// and then faded out over 50 ms, so a longer gap or a paused source ends in silence,
// not a loop. The first chunk after a gap is cross-faded in over 5 ms: it also hides
// the decoder's transient there (its first 2.5 ms overlap a frame it never decoded).
// Why the ramps: any other jump (a new offset, the start of the stream) is faded out
// and in over RAMP frames (2.7 ms) instead of cut.
export const WORKLET_NAME = "upcast-audio";

export const WORKLET_SOURCE = `
const RAMP = 128;
const KEEP_FRAMES = sampleRate * 2; // at most 2 s queued: a stalled clock cannot grow memory
const MIN_PERIOD = Math.round(sampleRate * 0.0025);
const MAX_PERIOD = Math.round(sampleRate * 0.015);
const MATCH = Math.round(sampleRate * 0.005); // samples compared at each candidate period
const HISTORY = MAX_PERIOD + MATCH;
const HOLD = Math.round(sampleRate * 0.01); // concealment at full level
const FADE = Math.round(sampleRate * 0.05); // then down to silence
const RESUME = Math.round(sampleRate * 0.005); // cross-fade from concealment to the stream
// Where the repeated period starts again (and where it first follows the played sound)
// the waveform does not quite continue (an integer period, a changing sound): the step
// against a straight-line continuation is spread over this many samples instead.
const JUNCTION = Math.round(sampleRate * 0.001);
// Below this correlation the sound is not periodic (noise, a transient): the longest
// period is repeated, a slower and less buzzy loop than a short one.
const PERIODIC = 0.3;
class UpcastAudio extends AudioWorkletProcessor {
	constructor() {
		super();
		this.chunks = []; // {start (media frames), data Float32Array}, sorted by start
		this.offset = null; // context frame - media frame; null until the page sets it
		this.pendingOffset = null;
		this.gain = 0;
		this.last = 0;
		this.history = new Float32Array(HISTORY); // what was played, a ring
		this.historyEnd = 0; // samples written into the ring
		this.historyValid = 0; // of which played without a silent break (at most HISTORY)
		// Allocated once: the audio thread should not make garbage.
		this.recent = new Float32Array(HISTORY); // the ring, oldest first, at a gap's start
		this.template = new Float32Array(MAX_PERIOD); // its first period samples repeat
		this.period = 0; // 0: no gap being concealed
		this.junction = 0; // its first sample less the straight-line continuation before it
		this.concealed = 0; // samples concealed in this gap
		this.resumed = -1; // samples into the cross-fade back, -1 outside one
		this.underrun = 0; // output frames without their sample while chunks were expected
		this.concealedTotal = 0; // output frames filled by concealment
		this.played = []; // media starts of chunks that began playing, with their context frame
		this.lastReport = 0;
		this.port.onmessage = (event) => {
			const m = event.data;
			if (m.type === "chunk") this.push(m.start, m.data);
			else if (m.type === "offset") this.pendingOffset = m.offset;
			else if (m.type === "reset") { this.chunks = []; this.forget(); }
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
				const s = c.data[i];
				return Number.isFinite(s) ? s : 0; // a broken decode must not poison the output
			}
		}
		return null;
	}
	forget() {
		this.historyValid = 0;
		this.period = 0;
		this.resumed = -1;
	}
	remember(v) {
		this.history[this.historyEnd % HISTORY] = v;
		this.historyEnd++;
		if (this.historyValid < HISTORY) this.historyValid++;
	}
	// The period to repeat: the lag whose last MATCH samples best match the MATCH before
	// the gap (normalised correlation); its last period is copied out as the template.
	startConcealment() {
		const x = this.recent;
		for (let i = 0; i < HISTORY; i++) x[i] = this.history[(this.historyEnd + i) % HISTORY];
		let energy = 0;
		for (let i = HISTORY - MATCH; i < HISTORY; i++) energy += x[i] * x[i];
		let best = MAX_PERIOD;
		let bestScore = PERIODIC;
		for (let p = MIN_PERIOD; p <= MAX_PERIOD; p++) {
			let c = 0, e = 0;
			for (let i = HISTORY - MATCH; i < HISTORY; i++) { const y = x[i - p]; c += x[i] * y; e += y * y; }
			const score = c / Math.sqrt(e * energy + 1e-30);
			if (score > bestScore) { bestScore = score; best = p; }
		}
		this.period = best;
		this.template.set(x.subarray(HISTORY - best));
		// A loop's start follows its own end: the same step at the first sample and at
		// every repeat.
		this.junction = this.template[0] - (2 * x[HISTORY - 1] - x[HISTORY - 2]);
		this.concealed = 0;
		this.resumed = -1;
	}
	concealment() {
		const n = this.concealed++;
		const level = n < HOLD ? 1 : Math.max(0, 1 - (n - HOLD) / FADE);
		const i = n % this.period;
		const v = this.template[i] - (i < JUNCTION ? this.junction * (1 - i / JUNCTION) : 0);
		return level * v;
	}
	process(inputs, outputs) {
		const out = outputs[0][0];
		const n = out.length;
		if (this.pendingOffset !== null) {
			if (this.offset === null || this.gain === 0) { this.offset = this.pendingOffset; this.pendingOffset = null; this.forget(); }
		}
		if (this.offset === null) { out.fill(0); return true; }
		const jumping = this.pendingOffset !== null; // fade out first, then move
		if (jumping) this.forget();
		let silent = 0;
		for (let k = 0; k < n; k++) {
			const media = currentFrame + k - this.offset;
			const s = jumping ? null : this.sampleAt(media);
			let v;
			if (s !== null) {
				v = s;
				if (this.period !== 0) {
					// The gap ended: fade from the concealment into the stream.
					if (this.resumed < 0) this.resumed = 0;
					const w = ++this.resumed / RESUME;
					v = w * s + (1 - w) * this.concealment();
					if (this.resumed >= RESUME) { this.period = 0; this.resumed = -1; }
				}
				if (this.gain < 1) this.gain = Math.min(1, this.gain + 1 / RAMP);
				this.remember(v);
				this.last = v;
			} else {
				silent++;
				if (!jumping && this.period === 0 && this.gain === 1 && this.historyValid === HISTORY) this.startConcealment();
				if (!jumping && this.period !== 0 && this.concealed >= HOLD + FADE) {
					// Faded out: silence until the stream is back (then a plain fade in).
					this.forget();
					this.gain = 0;
					this.last = 0;
				}
				if (!jumping && this.period !== 0) {
					this.resumed = -1; // lost again while fading back: conceal on
					v = this.concealment();
					this.concealedTotal++;
					this.remember(v);
					this.last = v;
				} else {
					// Nothing to conceal with: the last sample, faded out.
					if (this.gain > 0) this.gain = Math.max(0, this.gain - 1 / RAMP);
					v = this.last;
					this.last *= 0.98;
					this.historyValid = 0;
				}
			}
			out[k] = this.gain * v;
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
			this.port.postMessage({ type: "report", frame: currentFrame, offset: this.offset, buffered, underrun: this.underrun, concealed: this.concealedTotal, played: this.played });
			this.played = [];
		}
		return true;
	}
}
registerProcessor("${WORKLET_NAME}", UpcastAudio);
`;
