// Whether the player has focus: the viewer clicked the picture, so every game key and
// the pointer go to the game. Focus is the element's DOM focus (the canvas is focusable):
// a click on it takes focus, a click anywhere else gives it back. No key releases it,
// because games use all of them (escape opens their menus).

export class PlayerFocus {
	readonly #target: HTMLElement;
	/** Focus lost: release whatever the game thinks is held. */
	onBlur?: () => void;

	constructor(target: HTMLElement) {
		this.#target = target;
		if (target.tabIndex < 0) target.tabIndex = 0; // focusable by a click
		target.addEventListener("focus", () => this.#show(true));
		target.addEventListener("blur", () => {
			this.#show(false);
			this.onBlur?.();
		});
		this.#show(this.focused);
	}

	get focused(): boolean {
		return document.activeElement === this.#target || document.pointerLockElement === this.#target;
	}

	// An outline says the keyboard now goes to the game (the stylesheet hides the default).
	#show(on: boolean): void {
		this.#target.style.outline = on ? "2px solid #4af" : "";
		this.#target.style.outlineOffset = on ? "-2px" : "";
	}
}
