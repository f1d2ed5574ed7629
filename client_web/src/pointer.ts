// The pointer over the picture, absolute and with its buttons, for applications that
// take a mouse (menus, point-and-click): {type:"pointer", x, y, buttons}, x/y in 0..1
// of the displayed picture. Button changes go out at once (a click must not wait);
// moves are coalesced to one message per animation frame.

export type PointerState = { x: number; y: number; buttons: number };

/** Where the picture lies in client coordinates: the content box less any letterbox. */
export function pictureBox(element: HTMLElement): { left: number; top: number; width: number; height: number } {
	const rect = element.getBoundingClientRect();
	const style = getComputedStyle(element);
	const px = (v: string): number => parseFloat(v) || 0;
	const left = rect.left + px(style.borderLeftWidth) + px(style.paddingLeft);
	const top = rect.top + px(style.borderTopWidth) + px(style.paddingTop);
	const width = Math.max(0, rect.right - px(style.borderRightWidth) - px(style.paddingRight) - left);
	const height = Math.max(0, rect.bottom - px(style.borderBottomWidth) - px(style.paddingBottom) - top);
	const [iw, ih] = intrinsicSize(element);
	if (!iw || !ih || !width || !height) return { left, top, width, height };
	// object-fit decides the picture's size inside the box, object-position its place.
	const contain = Math.min(width / iw, height / ih);
	const scale: Record<string, number> = { contain, cover: Math.max(width / iw, height / ih), none: 1, "scale-down": Math.min(1, contain) };
	const fit = scale[style.objectFit];
	if (fit === undefined) return { left, top, width, height }; // "fill": stretched
	const pw = iw * fit;
	const ph = ih * fit;
	const [posX = "50%", posY = "50%"] = style.objectPosition.split(/\s+/);
	return { left: left + offset(posX, width - pw), top: top + offset(posY, height - ph), width: pw, height: ph };
}

function offset(position: string, free: number): number {
	if (position.endsWith("%")) return (free * parseFloat(position)) / 100;
	if (position.endsWith("px")) return parseFloat(position);
	return free / 2; // calc() and the like: centred, the default
}

function intrinsicSize(element: HTMLElement): [number, number] {
	if (element instanceof HTMLCanvasElement) return [element.width, element.height];
	if (element instanceof HTMLVideoElement) return [element.videoWidth, element.videoHeight];
	if (element instanceof HTMLImageElement) return [element.naturalWidth, element.naturalHeight];
	return [0, 0];
}

/** A client position -> 0..1 over the picture, clamped (a drag may leave it). */
export function pictureCoordinates(element: HTMLElement, clientX: number, clientY: number): { x: number; y: number } {
	const box = pictureBox(element);
	const unit = (v: number, size: number): number => (size > 0 ? Math.round(Math.min(1, Math.max(0, v / size)) * 1e4) / 1e4 : 0);
	return { x: unit(clientX - box.left, box.width), y: unit(clientY - box.top, box.height) };
}

export class PointerCapture {
	readonly #target: HTMLElement;
	readonly #send: (state: PointerState) => void;
	readonly #focused: () => boolean;
	// A button went down over the picture and is not all released yet: the drag is the
	// game's even outside the picture, with or without focus.
	#pressed = false;
	#last: PointerState = { x: 0, y: 0, buttons: 0 };
	#pending?: PointerState;
	#frame = 0;

	constructor(target: HTMLElement, send: (state: PointerState) => void, focused: () => boolean) {
		this.#target = target;
		this.#send = send;
		this.#focused = focused;
		target.addEventListener("pointerdown", this.#event);
		window.addEventListener("pointermove", this.#event);
		window.addEventListener("pointerup", this.#event);
		window.addEventListener("pointercancel", this.#release);
		// Right-click is a game button here, not the page's menu.
		target.addEventListener("contextmenu", (event) => event.preventDefault());
		// Middle-click would start the browser's autoscroll.
		target.addEventListener("mousedown", (event) => {
			if (event.button === 1) event.preventDefault();
		});
	}

	/** Focus lost or the page hidden: nothing stays pressed in the game. */
	release(): void {
		this.#release();
	}

	#release = (): void => {
		this.#pressed = false;
		this.#pending = undefined;
		if (this.#last.buttons !== 0) this.#emit({ ...this.#last, buttons: 0 });
	};

	#event = (event: PointerEvent): void => {
		const over = event.target === this.#target;
		if (event.type === "pointerdown" && over) this.#pressed = true;
		if (!this.#pressed && !(over && this.#focused())) return;
		// Locked, the position means nothing (look deltas carry the motion): buttons only.
		const locked = document.pointerLockElement === this.#target;
		const at = locked ? this.#last : pictureCoordinates(this.#target, event.clientX, event.clientY);
		const state = { x: at.x, y: at.y, buttons: event.buttons & 31 };
		if (state.buttons === 0) this.#pressed = false;
		if (state.buttons !== this.#last.buttons) {
			this.#pending = undefined;
			this.#emit(state);
		} else {
			// The newest position wins, even one back where the last message was.
			this.#pending = state;
			if (!this.#frame) this.#frame = requestAnimationFrame(this.#flush);
		}
	};

	#flush = (): void => {
		this.#frame = 0;
		const state = this.#pending;
		this.#pending = undefined;
		if (state && (state.x !== this.#last.x || state.y !== this.#last.y)) this.#emit(state);
	};

	#emit(state: PointerState): void {
		this.#last = state;
		this.#send(state);
	}
}
