// Stream controls in the page: upscaler, its cache policy, scale factor, frame generation,
// keyframe request.
// They travel on the same input track as keys and mouse (type "control"/"keyframe").
import type { InputPublisher } from "./input";

export const UPSCALERS = ["nearest", "bilinear", "bicubic", "lanczos2", "easu", "easu_rcas", "temporal", "unet", "unetpp", "unet_cached"] as const;
// Methods that read depth, motion and jitter (upscalers/names.py TEMPORAL_UPSCALERS): a
// captured application (source "x11") has none, so the page disables them there.
export const NEEDS_GBUFFERS = new Set(["temporal", "unet", "unetpp", "unet_cached"]);
const COLOR_ONLY_NOTE = "needs depth and motion, which a captured application does not give";
export const SCALES = [1.5, 2, 3] as const;
// Layer-cache policies of unet_cached (upscalers/cache/policies; any NAME@VALUE works too).
export const CACHE_POLICIES = ["delta_l", "delta_h", "budget", "budget@41", "every_2", "every_5", "deepcache", "motion"] as const;
const CACHED_UPSCALERS = new Set(["unet_cached"]);

/** Keeps the selects on what the server runs, except right after the viewer changed one. */
export interface Controls {
	follow(upscaler: unknown, scale: unknown, frameGeneration: unknown, cachePolicy: unknown, source?: unknown): void;
}

// After a viewer's change the server takes a moment to switch; until then its records
// still carry the old setting, which must not flip the select back.
const HOLD_MS = 3000;

export function mountControls(root: HTMLElement, publisher: InputPublisher, viewOnly = false): Controls {
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
	const cachePolicy = select(
		"cache-policy",
		CACHE_POLICIES.map((name) => [name, name]),
		"delta_l",
	);
	cachePolicy.title = "when the cached upscaler reuses its deep layers (only unet_cached has a cache)";
	// Only a method with a layer cache takes a policy; the server refuses it for the others.
	const enableCachePolicy = (): void => {
		cachePolicy.disabled = viewOnly || !CACHED_UPSCALERS.has(upscaler.value);
	};
	enableCachePolicy();
	let changedAt = -Infinity;
	let currentSource: unknown = undefined; // "game" or "x11", from the timing records
	upscaler.addEventListener("change", () => {
		changedAt = performance.now();
		enableCachePolicy();
		publisher.send({ type: "control", upscaler: upscaler.value });
	});
	cachePolicy.addEventListener("change", () => {
		changedAt = performance.now();
		publisher.send({ type: "control", cache_policy: cachePolicy.value });
	});
	scale.addEventListener("change", () => {
		changedAt = performance.now();
		publisher.send({ type: "control", scale: Number(scale.value) });
	});

	// Frame generation: the game renders every other frame and the server predicts the rest.
	const frameGeneration = document.createElement("input");
	frameGeneration.type = "checkbox";
	frameGeneration.id = "frame-generation";
	frameGeneration.title = "render every other frame, predict the rest (same stream fps)";
	frameGeneration.addEventListener("change", () => {
		changedAt = performance.now();
		publisher.send({ type: "control", frame_generation: frameGeneration.checked });
	});

	const keyframe = document.createElement("button");
	keyframe.type = "button";
	keyframe.id = "keyframe";
	keyframe.textContent = "keyframe";
	keyframe.title = "ask the encoder for a keyframe now";
	keyframe.addEventListener("click", () => publisher.send({ type: "keyframe" }));

	root.append(
		label("upscaler", upscaler),
		label("cache policy", cachePolicy),
		label("scale", scale),
		label("frame generation", frameGeneration),
		keyframe,
	);
	return {
		follow(serverUpscaler: unknown, serverScale: unknown, serverFrameGeneration: unknown, serverCachePolicy: unknown, source?: unknown): void {
			if (source !== undefined && source !== currentSource) {
				currentSource = source;
				const colorOnly = source !== "game";
				for (const option of upscaler.options) {
					option.disabled = colorOnly && NEEDS_GBUFFERS.has(option.value);
					option.title = option.disabled ? COLOR_ONLY_NOTE : "";
				}
				scale.disabled = viewOnly || colorOnly;
				scale.title = colorOnly ? "a captured application streams at the size it draws at" : "";
				frameGeneration.disabled = viewOnly || colorOnly;
				frameGeneration.title = colorOnly ? COLOR_ONLY_NOTE : "render every other frame, predict the rest (same stream fps)";
			}
			if (performance.now() - changedAt < HOLD_MS) return;
			if (typeof serverUpscaler === "string" && serverUpscaler !== upscaler.value) {
				if ([...upscaler.options].some((o) => o.value === serverUpscaler)) upscaler.value = serverUpscaler;
				enableCachePolicy();
			}
			if (typeof serverCachePolicy === "string" && serverCachePolicy !== cachePolicy.value) {
				// A policy set elsewhere (upcast control) may not be in the list: show it anyway.
				if (![...cachePolicy.options].some((o) => o.value === serverCachePolicy)) {
					const option = document.createElement("option");
					option.value = option.textContent = serverCachePolicy;
					cachePolicy.append(option);
				}
				cachePolicy.value = serverCachePolicy;
			}
			if (typeof serverScale === "number") {
				const match = [...scale.options].find((o) => Math.abs(Number(o.value) - serverScale) < 0.01);
				if (match && match.value !== scale.value) scale.value = match.value;
			}
			if (typeof serverFrameGeneration === "boolean") frameGeneration.checked = serverFrameGeneration;
		},
	};
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
	// Until the first timing record says what the server runs, preselect the usual
	// default; nothing is sent until the viewer changes it.
	element.value = initial;
	return element;
}

function label(text: string, control: HTMLElement): HTMLLabelElement {
	const element = document.createElement("label");
	element.append(`${text} `, control);
	return element;
}
