// Page settings from the query string, so one static bundle serves any relay.
// Defaults: the relay that served this page (its TCP side serves both these files and
// /certificate.sha256 on the QUIC port number), else port 4443 on the page's host;
// broadcast "game".

export interface Config {
	/** Relay URL given to @moq/lite connect(); http:// makes it pin /certificate.sha256. */
	url: URL;
	/** Broadcast name of the game session. */
	broadcast: string;
	/** Whether the stats overlay starts visible. */
	overlay: boolean;
	/**
	 * The page's `jwt` (a relay token), also put on `url` as `?jwt=`: browsers cannot set
	 * WebTransport headers, so the token rides in the URL (as with moq-relay). Without one
	 * the page watches as an anonymous viewer and sends no inputs.
	 */
	token: string | null;
}

export function readConfig(location: Location = window.location): Config {
	const query = new URLSearchParams(location.search);
	const host = location.hostname || "localhost";
	// An IPv6 literal needs brackets back in a URL.
	const hostPart = host.includes(":") && !host.startsWith("[") ? `[${host}]` : host;
	const port = query.get("port") ?? (location.protocol.startsWith("http") && location.port ? location.port : "4443");
	const relay = query.get("url") ?? query.get("relay") ?? `http://${hostPart}:${port}/`;
	const url = new URL(relay, location.href);
	const token = query.get("jwt") || null;
	if (token) url.searchParams.set("jwt", token);
	return {
		url,
		broadcast: query.get("broadcast") ?? query.get("name") ?? "game",
		overlay: query.get("overlay") !== "0",
		token,
	};
}
