// Consumes the game broadcast with @moq/lite: `catalog.json`, `timing` and one video
// track of the catalog (the caller chooses which: the first, the player's track, unless
// told otherwise). One call = one subscription epoch; it returns when the broadcast ends
// (tracks closed by the relay, connection lost, or stop()).
//
// Switching renditions (selectVideo) is seamless: the new track is subscribed while the
// old one keeps playing, and the page moves over when the new track's first frame (the
// start of a group: a keyframe) is here; then the old track is closed. Why not at once:
// the relay replays the new track's cached group at once, but that still takes a round
// trip and the group's transfer, during which the old track's frames are the only
// picture there is.
import { merge } from "@moq/json";
import * as Moq from "@moq/lite";
import type { AudioRendition } from "./audio";
import type { VideoRendition } from "./decoder";
import type { TimingRecord } from "./timing";

const { Signal } = Moq.Signals;

export const CATALOG_TRACK = "catalog.json";
export const TIMING_TRACK = "timing";

// moq-lite priority: higher is sent first when the link is congested. The catalog
// gates everything, timing is tiny, video is the bulk.
// Audio above video: it is tiny and a gap in sound is worse than a late frame.
const PRIORITY = { catalog: 4, timing: 2, audio: 3, video: 1 };

export interface MediaEvents {
	/** The rendition playing (at the start, after each catalog, after a hard switch): configure the decoder. */
	catalog(rendition: VideoRendition, catalog: unknown): void;
	/**
	 * The track to play, among the catalog's CMAF video renditions (in catalog order, at
	 * least one); asked at each catalog. Default: the first (the player's track).
	 */
	chooseVideo?(renditions: VideoRendition[], catalog: unknown): string | undefined;
	/**
	 * The video moved over to `rendition` (a switch, or a refetch of the same track):
	 * its first group's first frame, a keyframe, is the next video(). Reconfigure here.
	 */
	videoSwitched?(rendition: VideoRendition, from: string): void;
	/** A switch to `track` was given up: its subscription ended before a frame came. */
	videoSwitchFailed?(track: string, why: string): void;
	/** One moof+mdat; `gap` is true when groups were skipped before this group. */
	video(fragment: Uint8Array, gap: boolean): void;
	timing(record: TimingRecord): void;
	/** The catalog's Opus rendition (legacy container), when the broadcast has sound. */
	audioCatalog?(rendition: AudioRendition): void;
	/** One audio frame: varint pts (us) + Opus packet. */
	audio?(payload: Uint8Array): void;
	/** Counting only: groups never received (sequence gaps), reset, or cut short by a test fault. */
	groupSkipped(count: number): void;
	/**
	 * A video group ended before its FIN. `reset`: by the relay (it skips a viewer whose
	 * oldest unsent frame is older than its max latency); `fault`: cut by a test fault
	 * (both counted by groupSkipped); `left`: left unfinished for a newer group (not
	 * counted: its FIN may simply trail the next group's first frame; only a jump in
	 * the fragment numbers says frames were missing). `newerWaiting`: a newer group,
	 * which starts at a keyframe, is already here; if not, the next one may only start
	 * at a keyframe the player asks for.
	 */
	groupEnded?(why: string, kind: GroupEnd, newerWaiting: boolean): void;
}

export type GroupEnd = "reset" | "fault" | "left";

/**
 * Test faults (window.upcast.faults): the page acts as if the network had lost what
 * it throws away here, so the end-to-end tests can check recovery without a lossy link.
 */
export interface VideoFaults {
	/** Groups to cut short at their next frame (as a relay reset would). */
	dropGroups: number;
	/** Until this performance.now(), every video frame is thrown away (a blackout). */
	blackoutUntilMs: number;
	/** Frames to garble (the first NAL length of the sample made absurd): a decoder error. */
	corruptFrames: number;
}

/** A video subscription waiting for its first frame before it replaces the playing one. */
interface PendingVideo {
	track: Moq.Track;
	name: string;
}

export class MediaSubscription {
	readonly #broadcast: Moq.Broadcast;
	readonly #events: MediaEvents;
	#video?: Moq.Track;
	#videoName?: string;
	#pending?: PendingVideo;
	#renditions: VideoRendition[] = [];
	#audio?: Moq.Track;
	#audioName?: string;
	#stopped = false;
	/** Resolves with why the subscription ended. */
	readonly done: Promise<string>;

	readonly #faults?: VideoFaults;

	constructor(connection: Moq.Connection.Established, name: Moq.Path.Valid, events: MediaEvents, faults?: VideoFaults) {
		this.#events = events;
		this.#faults = faults;
		this.#broadcast = connection.consume(name);
		const catalog = this.#broadcast.subscribe(CATALOG_TRACK, PRIORITY.catalog);
		const timing = this.#broadcast.subscribe(TIMING_TRACK, PRIORITY.timing);
		// Either essential track ending ends the epoch; the caller decides to resubscribe.
		this.done = Promise.race([this.#runCatalog(catalog), this.#runTiming(timing)]).finally(() => this.stop());
	}

	stop(): void {
		if (this.#stopped) return;
		this.#stopped = true;
		this.#pending?.track.close();
		this.#pending = undefined;
		this.#video?.close();
		this.#audio?.close();
		this.#broadcast.close();
	}

	async #runCatalog(track: Moq.Track): Promise<string> {
		try {
			for (;;) {
				const group = await track.nextGroupOrdered();
				if (!group) return "catalog track ended";
				// First frame of a group: the whole catalog; later frames: RFC 7396 patches.
				let catalog = await group.readJson();
				if (catalog === undefined) continue;
				this.#onCatalog(catalog);
				for (;;) {
					const patch = await group.readJson();
					if (patch === undefined) break;
					catalog = merge(catalog, patch);
					this.#onCatalog(catalog);
				}
			}
		} catch (err) {
			return `catalog: ${errorText(err)}`;
		}
	}

	#onCatalog(catalog: unknown): void {
		const renditions = pickRenditions(catalog);
		if (renditions.length === 0) throw new Error("catalog has no CMAF video rendition");
		this.#renditions = renditions;
		const wanted = this.#events.chooseVideo?.(renditions, catalog);
		const rendition = renditions.find((r) => r.track === wanted) ?? renditions[0];
		const playing = renditions.find((r) => r.track === this.#videoName);
		if (this.#pending && !renditions.some((r) => r.track === this.#pending?.name)) {
			const name = this.#pending.name;
			this.#cancelPending();
			this.#events.videoSwitchFailed?.(name, "it left the catalog");
		}
		if (!playing) {
			// The start, or the playing track left the catalog (a new encoded size renamed
			// it): what is left of it was encoded for another decoder configuration, so
			// move at once.
			this.#cancelPending();
			this.#events.catalog(rendition, catalog);
			this.#video?.close();
			this.#videoName = rendition.track;
			this.#video = this.#broadcast.subscribe(rendition.track, PRIORITY.video);
			void this.#runVideo(this.#video);
		} else {
			this.#events.catalog(playing, catalog); // a no-op unless its configuration changed
			this.selectVideo(rendition.track);
		}
		const audio = pickAudio(catalog);
		if (audio && this.#events.audio && audio.track !== this.#audioName) {
			this.#events.audioCatalog?.(audio);
			this.#audio?.close();
			this.#audioName = audio.track;
			this.#audio = this.#broadcast.subscribe(audio.track, PRIORITY.audio);
			void this.#runAudio(this.#audio);
		}
	}

	/** The track playing now, and the one a switch waits for. */
	get videoTrack(): string | undefined {
		return this.#videoName;
	}

	get pendingTrack(): string | undefined {
		return this.#pending?.name;
	}

	/**
	 * Play `track` (a rendition of the last catalog): subscribe it and move over at its
	 * first frame; the playing track's name cancels a pending switch. False when the
	 * track is not in the catalog.
	 */
	selectVideo(track: string): boolean {
		if (this.#stopped) return false;
		if (track === this.#videoName) {
			this.#cancelPending();
			return true;
		}
		if (track === this.#pending?.name) return true;
		if (!this.#renditions.some((r) => r.track === track)) return false;
		this.#startPending(track);
		return true;
	}

	/**
	 * Subscribe the playing track again and move over at its first frame: the relay
	 * replays its latest group from the keyframe that starts it. A page that cannot ask
	 * the encoder for a keyframe (no token) gets one this way. False while a switch is
	 * pending (it brings a keyframe too) or nothing plays.
	 */
	refetchVideo(): boolean {
		if (this.#stopped || this.#pending || !this.#videoName) return false;
		this.#startPending(this.#videoName);
		return true;
	}

	#startPending(name: string): void {
		this.#cancelPending();
		const track = this.#broadcast.subscribe(name, PRIORITY.video);
		this.#pending = { track, name };
		void this.#runVideo(track);
	}

	#cancelPending(): void {
		this.#pending?.track.close();
		this.#pending = undefined;
	}

	// The pending track's first frame is here: it becomes the playing one.
	#promote(): void {
		const pending = this.#pending;
		if (!pending) return;
		const old = this.#video;
		const from = this.#videoName ?? "";
		this.#pending = undefined;
		this.#video = pending.track;
		this.#videoName = pending.name;
		const rendition = this.#renditions.find((r) => r.track === pending.name);
		if (rendition) this.#events.videoSwitched?.(rendition, from);
		old?.close();
	}

	// Every audio frame in order: readFrame() drains older groups before newer ones.
	// Audio never ends the epoch: video without sound is still worth showing.
	async #runAudio(track: Moq.Track): Promise<void> {
		try {
			for (;;) {
				const frame = await track.readFrame();
				if (!frame) return;
				this.#events.audio?.(frame);
			}
		} catch (err) {
			if (!this.#stopped) console.warn("upcast: audio track ended:", errorText(err));
		}
	}

	async #runTiming(track: Moq.Track): Promise<string> {
		try {
			for (;;) {
				// readFrame() drains older groups first, then moves on: no frame is lost.
				const frame = await track.readFrame();
				if (!frame) return "timing track ended";
				try {
					this.#events.timing(JSON.parse(new TextDecoder().decode(frame)) as TimingRecord);
				} catch (err) {
					console.warn("upcast: bad timing frame", err);
				}
			}
		} catch (err) {
			return `timing: ${errorText(err)}`;
		}
	}

	async #runVideo(track: Moq.Track): Promise<void> {
		let last: number | undefined;
		let why = "track ended";
		try {
			for (;;) {
				// The relay starts us at its latest group, which begins with a keyframe.
				const group = await track.nextGroupOrdered();
				if (!group) break;
				const gap = last !== undefined && group.sequence !== last + 1;
				if (gap && last !== undefined && track === this.#video) this.#events.groupSkipped(group.sequence - last - 1);
				last = group.sequence;
				await this.#readGroup(track, group, gap);
			}
		} catch (err) {
			why = errorText(err);
			if (!this.#stopped && track === this.#video) console.warn("upcast: video track ended:", why);
		}
		if (this.#stopped) return;
		if (track === this.#pending?.track) {
			// A switch whose track never delivered (refused, not found): stay where we are.
			const name = this.#pending.name;
			this.#pending = undefined;
			this.#events.videoSwitchFailed?.(name, why);
			return;
		}
		// Without video the epoch is useless: end it so the caller resubscribes.
		if (track === this.#video) this.stop();
	}

	// Reads one group; abandons it as soon as a newer group is waiting and nothing of
	// this one is buffered, because the newer group starts at a newer keyframe.
	// Why the group's signals and not readFrame(): a pending readFrame() raced against
	// "newer group" could consume a frame and lose it; peeking is synchronous.
	async #readGroup(track: Moq.Track, group: Moq.Group, gap: boolean): Promise<void> {
		let first = true;
		for (;;) {
			// A new catalog or a switch moved the video to another track: what is left of
			// this one was encoded for a decoder configured differently, or is not wanted.
			if (this.#stopped) return;
			const pending = track === this.#pending?.track;
			if (track !== this.#video && !pending) return;
			const frame = group.state.frames.peek().shift();
			if (frame && pending) {
				this.#promote(); // the new track's first frame, a keyframe: move over now
			}
			if (frame) {
				const fault = this.#fault();
				if (fault) {
					this.#events.groupSkipped(1);
					group.close();
					this.#events.groupEnded?.(fault, "fault", false);
					return;
				}
				this.#events.video(this.#corrupt(frame), gap && first);
				first = false;
				continue;
			}
			const closed = group.state.closed.peek();
			if (pending) {
				// Nothing of the new track has played yet: no skip to count, just go on.
				if (closed || track.state.closed.peek() || track.state.groups.peek().length > 0) return;
				await Signal.race(group.state.frames, group.state.closed, track.state.groups, track.state.closed);
				continue;
			}
			if (closed instanceof Error) {
				// Reset: the relay skipped us past the rest of this group.
				if (!this.#stopped && !track.state.closed.peek()) {
					this.#events.groupSkipped(1);
					this.#events.groupEnded?.(`group ${group.sequence} reset: ${closed.message}`, "reset", track.state.groups.peek().length > 0);
				}
				return;
			}
			if (closed) return; // FIN: the group is complete.
			if (track.state.closed.peek()) {
				group.close(); // the subscription ends: not a skip
				return;
			}
			if (track.state.groups.peek().length > 0) {
				group.close();
				this.#events.groupEnded?.(`group ${group.sequence} left for a newer one`, "left", true);
				return;
			}
			await Signal.race(group.state.frames, group.state.closed, track.state.groups, track.state.closed);
		}
	}

	#corrupt(frame: Uint8Array): Uint8Array {
		const faults = this.#faults;
		if (!faults || faults.corruptFrames <= 0) return frame;
		faults.corruptFrames--;
		const out = frame.slice();
		// The mdat payload starts with the first NAL's 4-byte length (AVCC).
		for (let i = 0; i + 12 <= out.length; i++) {
			if (out[i + 4] === 0x6d && out[i + 5] === 0x64 && out[i + 6] === 0x61 && out[i + 7] === 0x74) {
				out.set([0x7f, 0xff, 0xff, 0xff], i + 8);
				break;
			}
		}
		return out;
	}

	#fault(): string | undefined {
		const faults = this.#faults;
		if (!faults) return undefined;
		if (performance.now() < faults.blackoutUntilMs) return "blackout (test fault)";
		if (faults.dropGroups > 0) {
			faults.dropGroups--;
			return "group dropped (test fault)";
		}
		return undefined;
	}
}

/** The first CMAF video rendition of a hang catalog; its key is the track name. */
export function pickRendition(catalog: unknown): VideoRendition | undefined {
	return pickRenditions(catalog)[0];
}

/** Every CMAF video rendition of a hang catalog, in catalog order (the player's track
 * first, then the spectator rungs). */
export function pickRenditions(catalog: unknown): VideoRendition[] {
	const renditions = (catalog as { video?: { renditions?: Record<string, unknown> } })?.video?.renditions;
	if (!renditions || typeof renditions !== "object") return [];
	const out: VideoRendition[] = [];
	for (const [track, value] of Object.entries(renditions)) {
		const config = value as {
			codec?: string;
			container?: { kind?: string; init?: string };
			codedWidth?: number;
			codedHeight?: number;
			framerate?: number;
			bitrate?: number;
		};
		if (config?.container?.kind !== "cmaf" || !config.container.init || !config.codec) continue;
		out.push({
			track,
			codec: config.codec,
			init: config.container.init,
			codedWidth: config.codedWidth,
			codedHeight: config.codedHeight,
			framerate: typeof config.framerate === "number" ? config.framerate : undefined,
			bitrate: typeof config.bitrate === "number" ? config.bitrate : undefined,
		});
	}
	return out;
}

/** The first Opus rendition in the legacy container of a hang catalog, if any. */
export function pickAudio(catalog: unknown): AudioRendition | undefined {
	const renditions = (catalog as { audio?: { renditions?: Record<string, unknown> } })?.audio?.renditions;
	if (!renditions || typeof renditions !== "object") return undefined;
	for (const [track, value] of Object.entries(renditions)) {
		const c = value as { codec?: string; container?: { kind?: string }; sampleRate?: number; numberOfChannels?: number; jitter?: number };
		if (c?.codec !== "opus" || (c.container?.kind ?? "legacy") !== "legacy") continue;
		if (!c.sampleRate || !c.numberOfChannels) continue;
		return { track, codec: c.codec, sampleRate: c.sampleRate, numberOfChannels: c.numberOfChannels, jitter: c.jitter };
	}
	return undefined;
}

export function errorText(err: unknown): string {
	return err instanceof Error ? err.message : String(err);
}
