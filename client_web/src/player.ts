// The upcast player: glue between the connection loop, the media subscription, the
// decoder, the renderer, the overlay and the input publisher; plus window.upcast, the
// hooks the end-to-end tests read.
import * as Moq from "@moq/lite";
import { Abr, renditionParams } from "./abr";
import { AudioPlayer } from "./audio";
import { mountAudioControls } from "./audio_controls";
import { AudioTimingJoin, type AudioTimingRecord } from "./audio_timing";
import { wallMs, wallUs } from "./clock";
import { readConfig } from "./config";
import { Announcement, type Status, keepConnected, sleep } from "./connection";
import { mountControls } from "./controls";
import { Decoder, type VideoRendition } from "./decoder";
import { FEEDBACK_INTERVAL_MS, ReceiveStats } from "./feedback";
import { readFragmentHeader } from "./fragment";
import { InputCapture, InputPublisher } from "./input";
import { errorText, MediaSubscription, type VideoFaults } from "./media";
import { Overlay } from "./overlay";
import { Renderer } from "./renderer";
import { RenditionChoice } from "./rendition_choice";
import { SYNC_MS, VideoHold } from "./video_hold";
import { KeyframeRecovery } from "./recovery";
import { FpsMeter, StageLatency, type Stats } from "./stats";
import { InputToPhoton, TimingJoin } from "./timing";
import { canvasThumbnail } from "./thumbnail";

const MAX_ERRORS = 50;

function main(): void {
	const config = readConfig();
	const canvas = document.getElementById("screen") as HTMLCanvasElement;
	const statusLine = document.getElementById("status") as HTMLElement;

	const latency = new StageLatency();
	const timing = new TimingJoin(latency);
	const inputToPhoton = new InputToPhoton();
	const fps = new FpsMeter();
	const errors: string[] = [];
	const state = {
		status: "starting" as string,
		connected: false,
		version: undefined as string | undefined,
		subscribed: false,
		framesReceived: 0,
		feedbackSent: 0,
		/** Connections made to the relay (more than 1: it reconnected). */
		connections: 0,
		codec: undefined as string | undefined,
		lastPresentedFrameId: undefined as number | undefined,
		lastPresentedPtsUs: undefined as number | undefined,
		quality: undefined as Stats["quality"],
	};
	// Whether each of the last PREDICTED_WINDOW presented frames was predicted.
	const PREDICTED_WINDOW = 120;
	const predictedFlags: boolean[] = [];

	const error = (message: string): void => {
		console.error("upcast:", message);
		errors.push(message);
		if (errors.length > MAX_ERRORS) errors.shift();
	};
	window.addEventListener("error", (event) => error(`uncaught: ${event.message}`));
	window.addEventListener("unhandledrejection", (event) => error(`unhandled rejection: ${errorText(event.reason)}`));

	const setStatus = (status: Status | string, detail?: string): void => {
		state.status = detail ? `${status}: ${detail}` : status;
		state.connected = status === "connected" || status === "subscribed" || status === "waiting for broadcast";
		if (status === "connected") state.connections++;
		statusLine.textContent = state.status;
		statusLine.dataset.state = status;
		if (status === "failed") error(state.status);
	};

	// Sound: made now (suspended until the first gesture), fed once the catalog has audio.
	const audio = typeof AudioDecoder === "undefined" ? undefined : new AudioPlayer();
	let audioEnabled = false;
	const audioTiming = new AudioTimingJoin(latency);
	if (audio) {
		audio.onStamp = (ptsUs, stage, us) => audioTiming.stamp(ptsUs, stage, us);
		mountAudioControls(document.getElementById("bar") as HTMLElement, audio);
	}

	// What arrives on the video track, counted from the track itself (feedback.ts), and
	// the keyframe requests that get the picture going again after a loss (recovery.ts).
	const receive = new ReceiveStats();
	// Publishing inputs needs a token (put on `<broadcast>/input`); without one the relay
	// would close the whole session on the announce, so a tokenless page only watches.
	const viewOnly = config.token === null;
	// A page without a token cannot ask for keyframes: it refetches instead (recovery.ts).
	const recovery = new KeyframeRecovery({ canRequest: !viewOnly });
	const faults: VideoFaults = { dropGroups: 0, blackoutUntilMs: 0, corruptFrames: 0 };

	const renderer = new Renderer(canvas);
	renderer.onPresent = ({ ptsUs }) => {
		const perf = performance.now();
		receive.shown(ptsUs, perf);
		if (audio && audioEnabled) {
			audio.videoPresented(ptsUs, perf - hold.waitedMs(ptsUs));
			// A/V offset: the audio heard now minus the picture shown now (+: audio ahead).
			const heard = audio.audibleMsAt(perf);
			if (heard !== undefined && audio.bufferedMs > 0) latency.add("av_offset", heard - ptsUs / 1000);
		}
		const now = wallUs();
		fps.tick(now / 1000);
		timing.stamp(ptsUs, "present", now);
		state.lastPresentedPtsUs = ptsUs;
		// The record may still be on its way; then the id stays unknown for this frame.
		state.lastPresentedFrameId = timing.record(ptsUs)?.frame;
	};
	timing.onPresented = (record, presentUs) => {
		inputToPhoton.presented(record, presentUs);
		controls.follow(record.upscaler, record.scale, record.frame_generation, record.cache_policy, record.source);
		state.quality = {
			mode: record.quality,
			upscaler: record.upscaler,
			scale: record.scale,
			frameGeneration: record.frame_generation,
			frameRate: record.frame_rate,
			reason: record.quality_reason,
		};
		predictedFlags.push(record.predicted === true);
		if (predictedFlags.length > PREDICTED_WINDOW) predictedFlags.shift();
	};

	const hold = new VideoHold((frame) => renderer.push(frame));
	// The newest pts handed on to be shown: after a switch, older frames of the new
	// track are decoded for reference only (Decoder.catchUp).
	let newestShownPts: number | undefined;
	const decoder = new Decoder({
		frame: (frame) => {
			timing.stamp(frame.timestamp, "decode", wallUs());
			if (newestShownPts === undefined || frame.timestamp > newestShownPts) newestShownPts = frame.timestamp;
			hold.add(frame, audio && audioEnabled ? audio.videoWaitMs(frame.timestamp, SYNC_MS) : undefined);
		},
		error,
		needKey: (reason) => needKeyframe(reason),
	});

	const publisher = new InputPublisher(config.broadcast);
	const controlsRoot = document.getElementById("controls") as HTMLElement;
	const controls = mountControls(controlsRoot, publisher, viewOnly);
	if (viewOnly) {
		for (const control of controlsRoot.querySelectorAll<HTMLSelectElement | HTMLButtonElement | HTMLInputElement>("select, button, input")) {
			control.disabled = true;
		}
		const hint = document.querySelector(".hint");
		if (hint) hint.textContent = "view only: inputs are off (no token in the page URL)";
		console.info("upcast: no token: view only, inputs off");
	} else {
		const capture = new InputCapture(canvas, publisher);
		capture.onPress = (seq, sentMs) => inputToPhoton.press(seq, sentMs);
	}

	// Which rendition plays (rendition_choice.ts): a page with a token plays the catalog's
	// first, the player's track; a spectator chooses among the ladder's rungs with the
	// ABR (abr.ts). `?rendition=<track>` forces one, `?abr=off` keeps the first.
	const abr = new Abr();
	const choice = new RenditionChoice(renditionParams(window.location.search), viewOnly, abr);
	// The subscription of this epoch (switches and refetches go to it).
	let current: MediaSubscription | undefined;
	// mfhd numbers continue across a switch (each rung's encoder counts its own).
	let sequenceOffset = 0;
	let lastSequence: number | undefined;
	let resequence = false;

	// The video moved over to another track (or the same one, refetched): its first
	// group, a keyframe, comes next.
	const videoSwitched = (rendition: VideoRendition, from: string): void => {
		const now = performance.now();
		state.codec = rendition.codec;
		try {
			decoder.configure(rendition);
		} catch (err) {
			error(`configure ${rendition.codec}: ${errorText(err)}`);
		}
		decoder.gap(choice.switched(rendition, from, now));
		// The replayed group starts up to a GOP before what is on screen: decode it, show
		// only what is newer.
		decoder.catchUp(newestShownPts);
		resequence = true;
	};

	// Keyframe requests go out on the input track, like the page's button; a page
	// without a token cannot send them: it waits for the ladder's next group, and if
	// none comes it fetches the latest group again (recovery.ts).
	let recoveryTimer: ReturnType<typeof setTimeout> | undefined;
	const pumpRecovery = (): void => {
		const now = performance.now();
		if (recovery.poll(now)) {
			const waited = recovery.waitedMs(now).toFixed(0);
			if (recovery.action === "request") {
				publisher.send({ type: "keyframe" });
				console.info(`upcast: keyframe requested (${recovery.reason}, waiting ${waited} ms)`);
			} else if (current?.refetchVideo()) {
				console.info(`upcast: no keyframe for ${waited} ms (${recovery.reason}): fetching the latest group of ${current.videoTrack} again`);
			}
		}
		clearTimeout(recoveryTimer);
		const wait = recovery.wakeIn(now);
		recoveryTimer = wait === undefined ? undefined : setTimeout(pumpRecovery, wait);
	};
	function needKeyframe(reason: string): void {
		recovery.need(performance.now(), reason);
		pumpRecovery();
	}

	// Frames the page threw away for being behind: the renderer's newest-wins drops and
	// the decoder's queue overflows.
	const droppedLate = (): number => renderer.dropped + decoder.late;
	// The ABR's timers: a stall, a switch that never came, low fps, an up-switch due.
	setInterval(() => {
		if (choice.adaptive && state.subscribed) choice.apply(abr.poll(performance.now()), current);
	}, 250);

	setInterval(() => {
		// Only while playing, and only when the session listens: frames wait otherwise.
		if (viewOnly || !state.subscribed || publisher.subscribers === 0) return;
		publisher.send(receive.report(true, droppedLate()));
		state.feedbackSent++;
	}, FEEDBACK_INTERVAL_MS);

	const stats = (): Stats => ({
		...state,
		fps: fps.fps(wallMs()),
		framesDecoded: decoder.decoded,
		framesPresented: renderer.presented,
		dropped: renderer.dropped,
		framesLost: receive.lost,
		groupsSkipped: receive.skipped,
		freezes: receive.freezes,
		freezeMs: receive.freezeMs,
		longestFreezeMs: receive.longestGapMs,
		late: droppedLate() + receive.shownLate,
		bytesReceived: receive.bytes,
		timingGaps: timing.lost,
		recovery: {
			waiting: recovery.waiting,
			reason: recovery.reason,
			keyframeRequests: recovery.requests,
			recoveries: recovery.recoveries,
			lastRecoveryMs: recovery.lastRecoveryMs,
			refetches: recovery.refetches,
		},
		...choice.stats(current?.pendingTrack, decoder.hidden),
		skippedUndecodable: decoder.skipped,
		width: renderer.width,
		height: renderer.height,
		predictedShare: predictedFlags.length ? predictedFlags.filter(Boolean).length / predictedFlags.length : 0,
		quality: state.quality,
		// Feedback goes the same way but is not an input: counted apart (feedbackSent).
		inputsSent: publisher.sent - state.feedbackSent,
		inputPath: publisher.path,
		inputSubscribers: publisher.subscribers,
		latency: latency.summary(),
		inputToPhoton: {
			p50: inputToPhoton.window.percentile(50),
			p95: inputToPhoton.window.percentile(95),
			samples: inputToPhoton.window.samples,
		},
		audio: {
			enabled: audioEnabled,
			running: audio?.running ?? false,
			muted: audio?.muted ?? false,
			volume: audio?.volume ?? 0,
			packets: audio?.packets ?? 0,
			decoded: audio?.decoded ?? 0,
			bufferedMs: audio?.bufferedMs ?? 0,
			underrunFrames: audio?.underrunFrames ?? 0,
			concealedFrames: audio?.concealedFrames ?? 0,
			decoderErrors: audio?.decoderErrors ?? 0,
			decoderRestarts: audio?.decoderRestarts ?? 0,
			malformed: audio?.malformed ?? 0,
			sync: audio?.syncParts(),
			// Video frames that waited for their sound (lip sync), and their mean wait.
			videoHeld: hold.held,
			videoHeldMeanMs: hold.held ? hold.heldMs / hold.held : 0,
		},
		errors: [...errors],
	});

	new Overlay(document.getElementById("overlay") as HTMLElement, stats, config.overlay);

	(window as unknown as { upcast: unknown }).upcast = {
		config,
		stats,
		viewOnly,
		/** What the canvas shows right now and which server frame it is (same task). */
		snapshot: () => ({
			frameId: state.lastPresentedFrameId ?? null,
			ptsUs: state.lastPresentedPtsUs ?? null,
			width: canvas.width,
			height: canvas.height,
			dataUrl: canvas.toDataURL("image/png"),
		}),
		/** The same, as 4x4 block sums (thumbnail.ts): a few ms instead of a PNG's tens. */
		thumbnail: () => ({
			frameId: state.lastPresentedFrameId ?? null,
			ptsUs: state.lastPresentedPtsUs ?? null,
			...canvasThumbnail(canvas),
		}),
		/** The player's audio output (a GainNode) and its context: tests put an analyser on it. */
		audioOutput: () => audio?.output ?? null,
		/**
		 * Play this rendition (a track of the catalog) from now on, as `?rendition=` does;
		 * null: let the page choose (its ABR for a spectator, the first rendition for a
		 * player or with ?abr=off). False when the track is not in the catalog or nothing
		 * is subscribed.
		 */
		rendition: (track: string | null) => choice.select(track, current),
		/** Send an input message by hand (tests); returns it with seq and sent_ms. */
		send: (message: Parameters<InputPublisher["send"]>[0]) => publisher.send(message),
		/**
		 * Test faults: `dropGroup()` cuts the current video group short, `blackout(ms)`
		 * throws every video frame away for ms, `corrupt(n)` garbles the next n frames.
		 */
		faults: {
			dropGroup: (count = 1) => {
				faults.dropGroups += count;
			},
			blackout: (ms: number) => {
				faults.blackoutUntilMs = performance.now() + ms;
			},
			corrupt: (count = 1) => {
				faults.corruptFrames += count;
			},
		},
	};

	if (!window.isSecureContext || typeof WebTransport === "undefined" || !Decoder.supported()) {
		// Browsers only offer WebTransport and WebCodecs to https:// or localhost pages.
		setStatus("failed", "this page needs WebTransport and WebCodecs (a secure context: https:// or localhost)");
		return;
	}

	// Groups skipped or reset: counted, and for a spectator's ABR a reason to go down.
	const skipped = (count: number, why: string): void => {
		receive.groupsSkipped(count);
		if (choice.adaptive) choice.apply(abr.skipped(performance.now(), why), current);
	};

	const name = Moq.Path.from(config.broadcast);
	// A video group was left for a newer one; counted as skipped if frames are missing.
	let groupLeft = false;
	void keepConnected(config.url, {
		status: setStatus,
		run: async (connection, closed) => {
			state.version = connection.version;
			if (!viewOnly) publisher.attach(connection);
			try {
				await follow(connection, closed);
			} finally {
				publisher.detach();
				state.subscribed = false;
				state.version = undefined;
			}
		},
	});

	// Subscribe to the game broadcast until the connection closes; resubscribe when the
	// subscription ends or the broadcast is announced again after going away.
	async function follow(connection: Moq.Connection.Established, closed: Promise<string>): Promise<void> {
		const announcement = new Announcement(connection, name);
		let connectionOpen = true;
		void closed.then(() => {
			connectionOpen = false;
		});
		while (connectionOpen) {
			if (announcement.active === false) {
				setStatus("waiting for broadcast", config.broadcast);
				await Promise.race([announcement.changed(), closed]);
				continue;
			}
			const generation = announcement.generation;
			// The relay starts a subscription at its newest group, at a keyframe.
			receive.restart();
			recovery.reset();
			abr.restart();
			groupLeft = false;
			newestShownPts = undefined;
			decoder.catchUp(undefined);
			sequenceOffset = 0;
			lastSequence = undefined;
			resequence = false;
			const subscription = new MediaSubscription(connection, name, {
				catalog: (rendition) => {
					state.codec = rendition.codec;
					// The start, or a new catalog renamed the track (a new encoded size).
					if (choice.catalog(rendition.track)) resequence = true;
					try {
						decoder.configure(rendition);
					} catch (err) {
						error(`configure ${rendition.codec}: ${errorText(err)}`);
					}
				},
				chooseVideo: (renditions) => choice.choose(renditions),
				videoSwitched: (rendition, from) => videoSwitched(rendition, from),
				videoSwitchFailed: (track, why) => choice.switchFailed(track, why),
				video: (fragment, gap) => {
					state.framesReceived++;
					const left = groupLeft;
					groupLeft = false;
					const now = wallUs();
					const arrival = performance.now();
					const header = readFragmentHeader(fragment);
					const ptsUs = header ? decoder.ptsUs(header.decodeTime) : undefined;
					let sequence = header?.sequence;
					if (sequence !== undefined) {
						// After a switch the new track's numbers continue the old one's.
						if (resequence) sequenceOffset = lastSequence === undefined ? 0 : lastSequence + 1 - sequence;
						resequence = false;
						sequence += sequenceOffset;
						lastSequence = sequence;
					}
					const lost = receive.fragment(sequence, ptsUs, fragment.byteLength, arrival);
					// The group left for this one was cut short only if frames are missing.
					if (left && lost > 0) skipped(1, "a group left unfinished");
					if (gap || lost > 0) decoder.gap(gap ? "group skipped" : `${lost} frame(s) lost`);
					let keyframe = false;
					try {
						const decoded = decoder.decode(fragment);
						for (const pts of decoded.timestamps) timing.stamp(pts, "receive", now);
						keyframe = decoded.keyframe;
						if (decoded.keyframe) recovery.keyframe(performance.now());
					} catch (err) {
						error(`decode: ${errorText(err)}`);
						decoder.gap("decode error");
					}
					if (choice.adaptive) {
						choice.apply(abr.frame(arrival, fragment.byteLength, ptsUs ?? Number.NaN, keyframe), current);
						choice.apply(abr.late(arrival, decoder.late), current);
					}
					// A frame the decoder cannot use: ask for the keyframe it waits for.
					if (decoder.waitingForKey) needKeyframe(decoder.waitReason);
				},
				timing: (record) => {
					const kind = (record as { kind?: string }).kind;
					if (kind === "audio") audioTiming.addRecord(record as unknown as AudioTimingRecord);
					else if (kind === undefined) timing.addRecord(record);
				},
				audioCatalog: (rendition) => {
					if (!audio) return;
					try {
						audio.configure(rendition);
						audioEnabled = true;
					} catch (err) {
						error(`audio configure ${rendition.codec}: ${errorText(err)}`);
					}
				},
				audio: (payload) => {
					try {
						audio?.frame(payload);
					} catch (err) {
						error(`audio: ${errorText(err)}`);
					}
				},
				groupSkipped: (count) => skipped(count, `${count} group(s) skipped`),
				groupEnded: (why, kind, newerWaiting) => {
					if (kind === "left") {
						// Counted as skipped if the next group's first fragment shows a loss.
						groupLeft = true;
						return;
					}
					decoder.gap("group ended early");
					// The next group may only start at a keyframe nobody asked for yet.
					if (!newerWaiting) needKeyframe(why);
				},
			}, faults);
			current = subscription;
			state.subscribed = true;
			setStatus("subscribed", config.broadcast);
			console.info("upcast: subscribed to", config.broadcast);
			// Stop when the subscription ends, the broadcast goes (or comes back: its
			// publisher restarted) or the connection closes.
			let ended = false;
			const why = await Promise.race([
				subscription.done,
				closed,
				(async () => {
					while (!ended) {
						await announcement.changed();
						if (announcement.active === false) return "broadcast announced inactive";
						if (announcement.generation !== generation) return "broadcast announced again";
					}
					return "";
				})(),
			]);
			ended = true; // lets the announce watcher above finish at the next change
			subscription.stop();
			if (current === subscription) current = undefined;
			choice.stopped();
			state.subscribed = false;
			decoder.gap("resubscribe");
			recovery.reset();
			renderer.clear();
			audio?.reset();
			console.warn("upcast: subscription ended:", why);
			if (!connectionOpen) return;
			setStatus("waiting for broadcast", why);
			// Back off a little unless an announce says it is back.
			await Promise.race([sleep(1000), announcement.changed(), closed]);
		}
	}
}

main();
