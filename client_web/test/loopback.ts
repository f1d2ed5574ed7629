// Loopback test harness (dist/test/loopback.html): an in-page moq-lite "game server"
// connected to the real player through a fake WebTransport pair. It publishes `game`
// with catalog.json / video (CMAF built with @moq/hang from a WebCodecs H.264 encoder)
// / timing, and subscribes to the player's `game/input/<id>` broadcast, so a browser
// test exercises the whole player without a relay. Not part of the production page.
import { Cmaf } from "@moq/hang/container";
import * as Moq from "@moq/lite";
import { fakeTransportPair } from "./fake_transport";

const WIDTH = 320;
const HEIGHT = 180;
const FPS = 30;
const GOP = 15; // frames per group: a new group (and keyframe) twice a second

interface Harness {
	framesPublished: number;
	inputs: Record<string, unknown>[];
	lastInputSeq: number;
	/** frame id -> RGB the frame was painted with, to compare against snapshots. */
	colors: Record<number, [number, number, number]>;
	connections: number;
	/** Stop publishing `game` (announce inactive) / start again, to test resubscribe. */
	setLive(live: boolean): void;
	/** Close the fake connection, to test reconnect. */
	dropConnection(): void;
	errors: string[];
}

const harness: Harness = {
	framesPublished: 0,
	inputs: [],
	lastInputSeq: 0,
	colors: {},
	connections: 0,
	setLive,
	dropConnection: () => currentClient?.close(),
	errors: [],
};
(window as unknown as { loopback: Harness }).loopback = harness;

let server: Moq.Connection.Established | undefined;
let currentClient: WebTransport | undefined;
let game: Moq.Broadcast | undefined;
const subscribers: Record<string, Set<Moq.Track>> = {
	"catalog.json": new Set(),
	video: new Set(),
	timing: new Set(),
};
// Open groups per subscriber track; a subscriber joins at the next keyframe.
const openGroups = new Map<Moq.Track, Moq.Group>();
let catalogJson: string | undefined;

(window as unknown as { upcastTestTransport: (url: URL) => Promise<WebTransport> }).upcastTestTransport = async (url) => {
	const [client, serverSide] = fakeTransportPair("moq-lite-03");
	currentClient = client;
	server = await Moq.Connection.connect(url, { transport: serverSide });
	harness.connections++;
	publishGame();
	void collectInputs(server);
	return client;
};

function publishGame(): void {
	if (!server) return;
	game?.close();
	for (const set of Object.values(subscribers)) set.clear();
	openGroups.clear();
	game = new Moq.Broadcast();
	server.publish(Moq.Path.from("game"), game);
	void serveRequests(game);
}

function setLive(live: boolean): void {
	if (live) publishGame();
	else {
		game?.close();
		game = undefined;
	}
}

async function serveRequests(broadcast: Moq.Broadcast): Promise<void> {
	for (;;) {
		const request = await broadcast.requested().catch(() => undefined);
		if (!request) return;
		const track = request.track;
		const set = subscribers[track.name];
		if (!set) {
			track.close(new Error("not found"));
			continue;
		}
		set.add(track);
		void track.closed.finally(() => {
			set.delete(track);
			openGroups.delete(track);
		});
		if (track.name === "catalog.json" && catalogJson) {
			const group = track.appendGroup();
			group.writeString(catalogJson);
		}
	}
}

// Subscribes to every viewer input broadcast, like the game session does via a relay.
async function collectInputs(connection: Moq.Connection.Established): Promise<void> {
	const announced = connection.announced(Moq.Path.from("game/input"));
	for (;;) {
		const entry = await announced.next().catch(() => undefined);
		if (!entry) return;
		if (!entry.active) continue;
		const track = connection.consume(entry.path).subscribe("input", 0);
		void (async () => {
			for (;;) {
				const frame = await track.readFrame().catch(() => undefined);
				if (!frame) return;
				const message = JSON.parse(new TextDecoder().decode(frame)) as Record<string, unknown>;
				harness.inputs.push(message);
				harness.lastInputSeq = Math.max(harness.lastInputSeq, Number(message.seq ?? 0));
			}
		})();
	}
}

// ---- the "game": paint a frame, encode it, publish CMAF + timing ----

const canvas = new OffscreenCanvas(WIDTH, HEIGHT);
const ctx = canvas.getContext("2d") as OffscreenCanvasRenderingContext2D;
const pending = new Map<number, { frame: number; renderStart: number; renderEnd: number; encodeStart: number; inputSeq: number }>();
let sequence = 0;

const encoder = new VideoEncoder({
	output: (chunk, metadata) => {
		const description = metadata?.decoderConfig?.description;
		if (description && !catalogJson) {
			const avcc = new Uint8Array(description as ArrayBuffer);
			const init = Cmaf.createVideoInitSegment({
				codec: "avc1.42E01F",
				codedWidth: WIDTH,
				codedHeight: HEIGHT,
				description: Array.from(avcc, (b) => b.toString(16).padStart(2, "0")).join(""),
				container: { kind: "legacy" },
			} as never);
			catalogJson = JSON.stringify({
				video: {
					renditions: {
						video: {
							codec: "avc1.42E01F",
							container: { kind: "cmaf", init: btoa(String.fromCharCode(...init)) },
							codedWidth: WIDTH,
							codedHeight: HEIGHT,
							framerate: FPS,
						},
					},
				},
			});
			for (const track of subscribers["catalog.json"]) track.appendGroup().writeString(catalogJson);
		}
		const data = new Uint8Array(chunk.byteLength);
		chunk.copyTo(data);
		const info = pending.get(chunk.timestamp);
		pending.delete(chunk.timestamp);
		const encodeEnd = nowUs();
		const fragment = Cmaf.encodeDataSegment({
			data,
			timestamp: chunk.timestamp, // the init segment's timescale is 1 MHz: us
			duration: Math.round(1e6 / FPS),
			keyframe: chunk.type === "key",
			sequence: ++sequence,
		});
		const record = {
			frame: info?.frame ?? -1,
			pts_us: chunk.timestamp,
			keyframe: chunk.type === "key",
			predicted: false,
			input_seq: info?.inputSeq ?? 0,
			stamps: {
				render_start: info?.renderStart,
				render_end: info?.renderEnd,
				encode_start: info?.encodeStart,
				encode_end: encodeEnd,
				publish: nowUs(),
			},
		};
		const timing = new TextEncoder().encode(JSON.stringify(record));
		// Same group sequence on video and timing: a new group at each keyframe.
		for (const [name, payload] of [
			["video", fragment],
			["timing", timing],
		] as const) {
			for (const track of subscribers[name]) {
				let group = openGroups.get(track);
				if (chunk.type === "key") {
					group?.close();
					group = track.appendGroup();
					openGroups.set(track, group);
				}
				group?.writeFrame(payload);
			}
		}
		harness.framesPublished++;
	},
	error: (err) => harness.errors.push(`encoder: ${err.message}`),
});
encoder.configure({
	codec: "avc1.42E01F",
	width: WIDTH,
	height: HEIGHT,
	framerate: FPS,
	latencyMode: "realtime",
	avc: { format: "avc" },
});

let frameId = 0;
setInterval(() => {
	if (encoder.encodeQueueSize > 2) return;
	const id = frameId++;
	const renderStart = nowUs();
	// A flat colour per frame (plus the input seq as brightness) is easy to compare.
	const color: [number, number, number] = [(id * 37) % 256, (id * 91) % 256, 128];
	harness.colors[id] = color;
	ctx.fillStyle = `rgb(${color.join(",")})`;
	ctx.fillRect(0, 0, WIDTH, HEIGHT);
	const renderEnd = nowUs();
	const timestamp = Math.round((id * 1e6) / FPS);
	pending.set(timestamp, { frame: id, renderStart, renderEnd, encodeStart: nowUs(), inputSeq: harness.lastInputSeq });
	const frame = new VideoFrame(canvas, { timestamp });
	encoder.encode(frame, { keyFrame: id % GOP === 0 });
	frame.close();
}, 1000 / FPS);

function nowUs(): number {
	return Math.round((performance.timeOrigin + performance.now()) * 1000);
}
