// Stream controls in the page: upscaler, scale factor, keyframe request.
// They travel on the same input track as keys and mouse (type "control"/"keyframe").
import type { InputPublisher } from "./input";

export const UPSCALERS = ["nearest", "bilinear", "bicubic", "lanczos2", "easu", "easu_rcas", "temporal"] as const;
export const SCALES = [1.5, 2, 3] as const;

export function mountControls(root: HTMLElement, publisher: InputPublisher): void {
	const upscaler = select(
		"upscaler",
		UPSCALERS.map((name) => [name, name]),
		"easu_rcas",
	);
	const scale = select(
		"scale",
		SCALES.map((s) => [String(s), `${s}x`]),
		"2",
	);
	upscaler.addEventListener("change", () => publisher.send({ type: "control", upscaler: upscaler.value }));
	scale.addEventListener("change", () => publisher.send({ type: "control", scale: Number(scale.value) }));

	const keyframe = document.createElement("button");
	keyframe.type = "button";
	keyframe.id = "keyframe";
	keyframe.textContent = "keyframe";
	keyframe.title = "ask the encoder for a keyframe now";
	keyframe.addEventListener("click", () => publisher.send({ type: "keyframe" }));

	root.append(label("upscaler", upscaler), label("scale", scale), keyframe);
}

function select(id: string, options: [string, string][], initial: string): HTMLSelectElement {
	const element = document.createElement("select");
	element.id = id;
	for (const [value, text] of options) {
		const option = document.createElement("option");
		option.value = value;
		option.textContent = text;
		element.append(option);
	}
	// The page does not know the server's current setting; this only preselects the
	// usual default and sends nothing until the viewer changes it.
	element.value = initial;
	return element;
}

function label(text: string, control: HTMLElement): HTMLLabelElement {
	const element = document.createElement("label");
	element.append(`${text} `, control);
	return element;
}
