// The sound controls: a mute button and a volume slider. Outside the stream controls
// on purpose: a view-only page (no token) has its controls disabled, but may listen.
import type { AudioPlayer } from "./audio";

export function mountAudioControls(root: HTMLElement, audio: AudioPlayer): void {
	const span = document.createElement("span");
	span.id = "audio-controls";
	const mute = document.createElement("button");
	mute.id = "audio-mute";
	mute.type = "button";
	const volume = document.createElement("input");
	volume.id = "audio-volume";
	volume.type = "range";
	volume.min = "0";
	volume.max = "1";
	volume.step = "0.05";
	volume.value = String(audio.volume);
	volume.title = "volume";
	const label = (): void => {
		// Until the first gesture the browser keeps the context suspended: say so.
		mute.textContent = !audio.running ? "sound: click" : audio.muted ? "sound: off" : "sound: on";
	};
	mute.addEventListener("click", () => {
		// The click that starts the sound only starts it; later ones toggle. Asked of the
		// state when the gesture began: by "click" the context may be running already.
		if (!audio.runningAtLastGesture) audio.setMuted(false);
		else audio.setMuted(!audio.muted);
		label();
	});
	volume.addEventListener("input", () => audio.setVolume(Number(volume.value)));
	audio.context.addEventListener("statechange", label);
	label();
	span.append(mute, volume);
	root.append(span);
}
