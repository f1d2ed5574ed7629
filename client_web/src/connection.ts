// Keeps a moq-lite connection to the relay and follows the game broadcast on it.
// Why a loop and not a page reload: the relay, the game or the network can go away and
// come back; the page reconnects with back-off and resubscribes when the broadcast is
// announced again, keeping its input id and its statistics.
import * as Moq from "@moq/lite";
import { errorText } from "./media";

export type Status = "connecting" | "connected" | "waiting for broadcast" | "subscribed" | "failed" | "disconnected";

export interface ConnectionEvents {
	status(status: Status, detail?: string): void;
	/** Runs for the life of one connection; resolve or throw to drop it. */
	run(connection: Moq.Connection.Established, closed: Promise<string>): Promise<void>;
}

/**
 * Test seam: a page may define `window.upcastTestTransport(url)` returning a
 * WebTransport-like session (dist/test/loopback.html wires the player to an in-page
 * moq-lite publisher this way, no relay needed). Unset in normal use.
 */
function testTransport(url: URL): Promise<WebTransport> | undefined {
	return (globalThis as { upcastTestTransport?: (url: URL) => Promise<WebTransport> }).upcastTestTransport?.(url);
}

const MIN_BACKOFF_MS = 500;
const MAX_BACKOFF_MS = 5000;

export async function keepConnected(url: URL, events: ConnectionEvents): Promise<never> {
	let backoff = MIN_BACKOFF_MS;
	for (;;) {
		events.status("connecting", redacted(url));
		let connection: Moq.Connection.Established;
		try {
			// For an http:// URL @moq/lite fetches /certificate.sha256 from the same host and
			// port and pins it (serverCertificateHashes). Our relay has no WebSocket side, so
			// the WebSocket fallback race is disabled instead of failing 500 ms later.
			const transport = await testTransport(url);
			connection = await Moq.Connection.connect(url, transport ? { transport } : { websocket: { enabled: false } });
		} catch (err) {
			events.status("failed", `${redacted(url)} unreachable: ${describeConnectError(err)}`);
			await sleep(backoff);
			backoff = Math.min(backoff * 2, MAX_BACKOFF_MS);
			continue;
		}
		backoff = MIN_BACKOFF_MS;
		console.info("upcast: connected to", redacted(url), "version", connection.version);
		events.status("connected", connection.version);
		const closed = connection.closed.then(
			() => "connection closed",
			(err) => `connection lost: ${errorText(err)}`,
		);
		try {
			await events.run(connection, closed);
		} catch (err) {
			console.warn("upcast: session ended:", err);
		}
		connection.close();
		const why = await Promise.race([closed, sleep(0).then(() => "closed by the page")]);
		console.warn("upcast: disconnected:", why);
		events.status("disconnected", why);
		await sleep(backoff);
	}
}

/** Announce state of one broadcast, fed by an announce-interest stream. */
export class Announcement {
	/** undefined until the relay says anything (it may not support announces at all). */
	active?: boolean;
	/** Bumped when the broadcast comes back after being announced inactive. */
	generation = 0;
	#waiters: (() => void)[] = [];

	constructor(connection: Moq.Connection.Established, name: Moq.Path.Valid) {
		void this.#run(connection.announced(name), name);
	}

	async #run(announced: Moq.Announced, name: Moq.Path.Valid): Promise<void> {
		try {
			for (;;) {
				const entry = await announced.next();
				if (!entry) return;
				// The prefix also matches `<name>/input/...` (viewers' input broadcasts).
				if (entry.path !== name) continue;
				console.info(`upcast: broadcast ${name} announced ${entry.active ? "active" : "inactive"}`);
				if (entry.active && this.active === false) this.generation++;
				this.active = entry.active;
				this.#wake();
			}
		} catch (err) {
			// Not fatal: subscribing directly still works without announces.
			console.info("upcast: announce stream ended:", errorText(err));
		}
	}

	/** Resolves at the next announce change. */
	changed(): Promise<void> {
		return new Promise((resolve) => this.#waiters.push(resolve));
	}

	#wake(): void {
		const waiters = this.#waiters;
		this.#waiters = [];
		for (const wake of waiters) wake();
	}
}

/** The URL without its token, for the status line and the console. */
function redacted(url: URL): string {
	if (!url.searchParams.has("jwt")) return url.toString();
	const copy = new URL(url);
	copy.searchParams.set("jwt", "...");
	return copy.toString();
}

export function sleep(ms: number): Promise<void> {
	return new Promise((resolve) => setTimeout(resolve, ms));
}

function describeConnectError(err: unknown): string {
	// Promise.any inside connect() wraps the real cause in an AggregateError.
	if (err instanceof AggregateError && err.errors.length > 0) return err.errors.map(errorText).join("; ");
	return errorText(err);
}
