// Interop page: the UNMODIFIED <moq-watch> web component from @moq/watch, pointed at
// our relay, to prove the stream plays in a stock moq-lite/hang player too.
import "@moq/watch/element";

const query = new URLSearchParams(window.location.search);
const host = window.location.hostname || "localhost";
const hostPart = host.includes(":") && !host.startsWith("[") ? `[${host}]` : host;
const port = query.get("port") ?? (window.location.protocol.startsWith("http") && window.location.port ? window.location.port : "4443");
const url = query.get("url") ?? `http://${hostPart}:${port}/`;
const name = query.get("broadcast") ?? query.get("name") ?? "game";

const element = document.createElement("moq-watch");
element.setAttribute("url", url);
element.setAttribute("name", name);
element.setAttribute("visible", "always");
// Muted unless the URL asks for sound (?muted=0): a page that plays sound by itself is
// what browsers block; with ?muted=0 sound starts at the first click, as browsers require.
if (query.get("muted") !== "0") element.setAttribute("muted", "");
element.append(document.createElement("canvas"));
document.getElementById("player")?.append(element);

const status = document.getElementById("status") as HTMLElement;
status.textContent = `connecting to ${url} broadcast ${name}`;
// The element exposes its connection state as a signal; show it for humans and tests.
const connection = (element as unknown as { connection?: { status?: { peek(): string } } }).connection;
setInterval(() => {
	const now = connection?.status?.peek?.();
	if (now) {
		status.textContent = `${now}: ${url} broadcast ${name}`;
		status.dataset.state = now;
	}
}, 250);
