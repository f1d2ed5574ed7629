// The stats overlay: text only, redrawn a few times a second (not per frame: layout
// work on every frame would itself cost presentation time). Toggled with "o"/F2.
import { STAGES, type Stats } from "./stats";

export class Overlay {
	readonly #element: HTMLElement;
	readonly #stats: () => Stats;
	#timer = 0;

	constructor(element: HTMLElement, stats: () => Stats, visible: boolean) {
		this.#element = element;
		this.#stats = stats;
		this.visible = visible;
		window.addEventListener("keydown", (event) => {
			// A key the player took for the game (focus on the picture) is the game's.
			if (event.defaultPrevented) return;
			if (event.key === "o" || event.key === "F2") this.visible = !this.visible;
		});
	}

	get visible(): boolean {
		return !this.#element.hidden;
	}

	set visible(on: boolean) {
		this.#element.hidden = !on;
		clearInterval(this.#timer);
		if (on) {
			this.#render();
			this.#timer = window.setInterval(() => this.#render(), 250);
		}
	}

	#render(): void {
		const s = this.#stats();
		const lines = [
			`${s.status}${s.connected ? ` (${s.version})` : ""}`,
			`fps ${s.fps}  ${s.width}x${s.height}  ${s.codec ?? "-"}  predicted ${Math.round(s.predictedShare * 100)}%`,
			`frames recv ${s.framesReceived}  dec ${s.framesDecoded}  shown ${s.framesPresented}  dropped ${s.dropped}`,
			`lost ${s.framesLost}  skipped groups ${s.groupsSkipped}  late ${s.late}  freezes ${s.freezes} (${(s.freezeMs / 1000).toFixed(1)} s)`,
			`keyframes asked ${s.recovery.keyframeRequests}${s.recovery.waiting ? ` (waiting: ${s.recovery.reason})` : ""}  recovered ${s.recovery.recoveries}${s.recovery.lastRecoveryMs === undefined ? "" : ` last ${s.recovery.lastRecoveryMs.toFixed(0)} ms`}`,
			rendition(s),
			quality(s.quality),
			`frame id ${s.lastPresentedFrameId ?? "-"}  inputs ${s.inputsSent}  feedback ${s.feedbackSent}  recv ${(s.bytesReceived / 1e6).toFixed(1)} MB`,
			s.audio.enabled
				? `audio ${s.audio.running ? (s.audio.muted ? "muted" : `on ${Math.round(s.audio.volume * 100)}%`) : "click to start"}  packets ${s.audio.packets}  buffered ${s.audio.bufferedMs.toFixed(0)} ms  underrun ${s.audio.underrunFrames}  concealed ${s.audio.concealedFrames}`
				: "audio -",
			"",
			"latency ms        p50     p95",
		];
		for (const stage of STAGES) {
			const l = s.latency[stage];
			if (stage.startsWith("audio") || stage === "av_offset") {
				if (!l?.n) continue; // no audio: keep the overlay as it was
			}
			lines.push(`${stage.padEnd(15)} ${fmt(l?.p50)} ${fmt(l?.p95)}`);
		}
		lines.push(`${"input->photon".padEnd(15)} ${fmt(s.inputToPhoton.p50)} ${fmt(s.inputToPhoton.p95)}`);
		if (s.errors.length > 0) lines.push("", `last error: ${s.errors[s.errors.length - 1]}`);
		this.#element.textContent = lines.join("\n");
	}
}

/** "rendition video.640x360 (abr, 2 switches, ~3.1 Mbit/s): up: ...": what plays and why. */
function rendition(s: Stats): string {
	const a = s.abr;
	const pending = a.pending ? ` -> ${a.pending}` : "";
	const estimate = a.estimateBps === undefined ? "" : `, ~${(a.estimateBps / 1e6).toFixed(1)} Mbit/s`;
	const why = a.mode === "abr" && a.reason ? `: ${a.reason}` : "";
	return `rendition ${s.rendition ?? "-"}${pending} (${a.mode}, ${s.renditionSwitches} switches${estimate})${why}`;
}

/** "quality auto: temporal at 2x, 30 fps (+0.31 dB expected ...)": the setting and why. */
function quality(q: Stats["quality"]): string {
	if (!q?.mode) return "quality -";
	const fg = q.frameGeneration ? ", frame generation" : "";
	const scale = q.scale === undefined ? "" : ` at ${q.scale}x`;
	const rate = q.frameRate === undefined ? "" : `, ${q.frameRate} fps`;
	return `quality ${q.mode}: ${q.upscaler ?? "-"}${scale}${fg}${rate}${q.reason ? ` (${q.reason})` : ""}`;
}

function fmt(value: number | undefined): string {
	return (value === undefined ? "-" : value.toFixed(1)).padStart(7);
}
