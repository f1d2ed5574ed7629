// Which rendition of the catalog the page plays, and the bookkeeping around it: the
// mode, the forced track, the switch asked for (when and why, for the log line and the
// time it took), seconds per track, the switches made. The ABR itself (abr.ts) decides
// for a spectator; this applies its decisions to the subscription and keeps the record
// the stats and the end-to-end tests read. The decoder and the mfhd numbering stay
// with the player: switched() says which gap the decoder is to see.
import { type Abr, type AbrDecision, formatBps, spectatorLadder } from "./abr";
import type { VideoRendition } from "./decoder";
import type { MediaSubscription } from "./media";
import type { Stats } from "./stats";

/** How the rendition is chosen: "player" (a token: the catalog's first, the player's
 * track), "abr" (a spectator), "forced" (?rendition= or the page hook), "first"
 * (a spectator with ?abr=off). */
export type RenditionMode = "abr" | "forced" | "first" | "player";

/** What the choice needs of the subscription (media.ts), so a test can stub it. */
export type VideoTracks = Pick<MediaSubscription, "videoTrack" | "selectVideo">;

/** The switch last made, for the stats. */
export interface RenditionSwitch {
	from: string;
	to: string;
	reason: string;
	tookMs?: number;
}

export class RenditionChoice {
	readonly #abr: Abr;
	// What `rendition(null)` goes back to: the page's own choice without ?rendition=.
	readonly #auto: RenditionMode;
	#mode: RenditionMode;
	#forced?: string;
	// The forced track last warned about, so a catalog that keeps missing it warns once.
	#forcedMissing?: string;
	#ladder: string[] = [];
	// The track playing, since when (performance.now()), and seconds per track before it.
	#track?: string;
	#since = 0;
	#seconds: Record<string, number> = {};
	#switches = 0;
	// When the pending switch was asked for, and why: its log line says how long it took.
	#askedAt?: number;
	#askedWhy?: string;
	#lastSwitch?: RenditionSwitch;

	/**
	 * `params` from the page's URL (abr.ts renditionParams); `viewOnly`: no token, a
	 * spectator, who chooses among the ladder's rungs with `abr` unless ?abr=off.
	 */
	constructor(params: { forced?: string; abrOff: boolean }, viewOnly: boolean, abr: Abr) {
		this.#abr = abr;
		this.#auto = viewOnly && !params.abrOff ? "abr" : viewOnly ? "first" : "player";
		this.#mode = params.forced ? "forced" : this.#auto;
		this.#forced = params.forced;
	}

	get mode(): RenditionMode {
		return this.#mode;
	}

	/** Whether the ABR chooses now: only then is it fed measurements. */
	get adaptive(): boolean {
		return this.#mode === "abr";
	}

	/** The track playing, undefined between subscriptions. */
	get track(): string | undefined {
		return this.#track;
	}

	/** A catalog (media.ts chooseVideo): the track to play among its renditions. */
	choose(renditions: VideoRendition[], now = performance.now()): string | undefined {
		this.#ladder = renditions.map((r) => r.track);
		if (this.#mode === "forced" && this.#forced !== undefined) {
			if (renditions.some((r) => r.track === this.#forced)) return this.#forced;
			if (this.#forcedMissing !== this.#forced) {
				this.#forcedMissing = this.#forced;
				console.warn(`upcast: rendition ${this.#forced} is not in the catalog (${this.#ladder.join(", ")}): playing ${renditions[0].track}`);
			}
			return renditions[0].track;
		}
		if (this.#mode !== "abr") return renditions[0].track;
		// A spectator plays the rungs only (abr.ts says why): they are its ladder.
		const rungs = spectatorLadder(renditions);
		this.#ladder = rungs.map((r) => r.track);
		const before = this.#abr.playing;
		const track = this.#abr.setLadder(rungs, now);
		if (track !== undefined && this.#abr.playing !== before) {
			console.info(`upcast: rendition ${track} (${this.#abr.reason}; ladder ${rungs.map((r) => `${r.track} ${formatBps(r.bitrate)}`).join(", ")})`);
		}
		return track;
	}

	/** Carry out an ABR decision on the subscription; ignored unless the ABR chooses. */
	apply(decision: AbrDecision | undefined, subscription: VideoTracks | undefined, now = performance.now()): void {
		if (!decision || this.#mode !== "abr" || !subscription) return;
		const from = subscription.videoTrack;
		if (decision.direction === "back") {
			console.info(`upcast: rendition stays ${decision.track} (${decision.reason})`);
		} else {
			console.info(`upcast: rendition ${from} -> ${decision.track} (${decision.reason})`);
			this.#askedAt = now;
			this.#askedWhy = decision.reason;
		}
		if (!subscription.selectVideo(decision.track)) this.#abr.switchFailed(now, decision.track, "not in the catalog");
	}

	/**
	 * Play `track` from now on (null: let the page choose: its ABR for a spectator, the
	 * first rendition otherwise); window.upcast.rendition. False when the track is not
	 * in the catalog or nothing is subscribed.
	 */
	select(track: string | null, subscription: VideoTracks | undefined, now = performance.now()): boolean {
		if (track === null) {
			this.#mode = this.#auto;
			this.#forced = undefined;
			const back = this.#mode === "abr" ? this.#abr.target : this.#ladder[0];
			return back === undefined || (subscription?.selectVideo(back) ?? false);
		}
		this.#mode = "forced";
		this.#forced = track;
		this.#askedAt = now;
		this.#askedWhy = "asked by the page";
		console.info(`upcast: rendition ${subscription?.videoTrack} -> ${track} (asked by the page)`);
		return subscription?.selectVideo(track) ?? false;
	}

	/**
	 * The catalog's track plays (media.ts catalog): the start, or a new catalog that
	 * renamed it (a new encoded size). True when another track played before it: its
	 * mfhd numbers start over, and the player continues them.
	 */
	catalog(track: string, now = performance.now()): boolean {
		if (track === this.#track) return false;
		const renamed = this.#track !== undefined;
		this.#playing(track, now);
		return renamed;
	}

	/**
	 * The video moved over to `rendition` from `from` (its first group arrived); the same
	 * track again is a refetch, not a switch. Returns the gap the decoder is to see.
	 */
	switched(rendition: VideoRendition, from: string, now = performance.now()): "switch" | "refetch" {
		this.#abr.switched(now, rendition.track);
		this.#playing(rendition.track, now);
		const took = this.#askedAt === undefined ? undefined : now - this.#askedAt;
		if (rendition.track === from) {
			console.info(`upcast: rendition ${rendition.track} fetched again from its latest group`);
		} else {
			this.#switches++;
			const reason = this.#askedWhy ?? "catalog";
			this.#lastSwitch = { from, to: rendition.track, reason, tookMs: took };
			console.info(`upcast: rendition now ${rendition.track} (switch ${this.#switches}, from ${from}${took === undefined ? "" : `, ${took.toFixed(0)} ms after asking`}: ${reason})`);
		}
		this.#askedAt = undefined;
		this.#askedWhy = undefined;
		return rendition.track === from ? "refetch" : "switch";
	}

	/** The switch to `track` ended without a frame (media.ts videoSwitchFailed). */
	switchFailed(track: string, why: string, now = performance.now()): void {
		console.warn(`upcast: rendition ${track} not played: ${why}`);
		this.#askedAt = undefined;
		this.#askedWhy = undefined;
		this.#abr.switchFailed(now, track, why);
	}

	/** The subscription ended: nothing plays until the next one's catalog. */
	stopped(now = performance.now()): void {
		this.#playing(undefined, now);
	}

	/** Seconds each track has played since the page loaded, to the hundredth. */
	seconds(now = performance.now()): Record<string, number> {
		const out = { ...this.#seconds };
		if (this.#track !== undefined) out[this.#track] = (out[this.#track] ?? 0) + (now - this.#since) / 1000;
		for (const key of Object.keys(out)) out[key] = Math.round(out[key] * 100) / 100;
		return out;
	}

	/** The page's rendition stats; `pending` and `hiddenFrames` come from the
	 * subscription and the decoder. */
	stats(pending: string | undefined, hiddenFrames: number, now = performance.now()): Pick<Stats, "rendition" | "renditionSwitches" | "renditionSeconds" | "abr"> {
		return {
			rendition: this.#track,
			renditionSwitches: this.#switches,
			renditionSeconds: this.seconds(now),
			abr: {
				mode: this.#mode,
				pending,
				reason: this.#mode === "abr" ? this.#abr.reason : this.#mode === "forced" ? `forced: ${this.#forced}` : this.#mode,
				estimateBps: this.#abr.estimate(now),
				holdMs: this.#abr.holdMs,
				failedUps: this.#abr.failedUps,
				ladder: [...this.#ladder],
				lastSwitch: this.#lastSwitch,
				hiddenFrames,
			},
		};
	}

	#playing(track: string | undefined, now: number): void {
		if (this.#track !== undefined) this.#seconds[this.#track] = (this.#seconds[this.#track] ?? 0) + (now - this.#since) / 1000;
		this.#track = track;
		this.#since = now;
	}
}
