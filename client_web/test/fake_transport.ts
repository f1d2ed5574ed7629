// A WebTransport-shaped pair of in-memory sessions, for the loopback test page only.
// Each side sees the other's streams as incoming streams. Chunks are copied because
// @moq/lite reuses a scratch buffer for varints after write() resolves.

type Bidi = { readable: ReadableStream<Uint8Array>; writable: WritableStream<Uint8Array> };

function pipe(): TransformStream<Uint8Array, Uint8Array> {
	return new TransformStream({ transform: (chunk, controller) => controller.enqueue(chunk.slice()) });
}

class Side {
	readonly protocol: string;
	readonly ready = Promise.resolve();
	readonly closed: Promise<WebTransportCloseInfo>;
	#closeResolve!: (info: WebTransportCloseInfo) => void;
	peer!: Side;
	readonly incomingBidirectionalStreams: ReadableStream<Bidi>;
	readonly incomingUnidirectionalStreams: ReadableStream<ReadableStream<Uint8Array>>;
	#bidi!: ReadableStreamDefaultController<Bidi>;
	#uni!: ReadableStreamDefaultController<ReadableStream<Uint8Array>>;
	#isClosed = false;

	constructor(protocol: string) {
		this.protocol = protocol;
		this.closed = new Promise((resolve) => {
			this.#closeResolve = resolve;
		});
		this.incomingBidirectionalStreams = new ReadableStream({ start: (c) => void (this.#bidi = c) });
		this.incomingUnidirectionalStreams = new ReadableStream({ start: (c) => void (this.#uni = c) });
	}

	async createBidirectionalStream(): Promise<Bidi> {
		const out = pipe();
		const back = pipe();
		this.peer.#bidi.enqueue({ readable: out.readable, writable: back.writable });
		return { readable: back.readable, writable: out.writable };
	}

	async createUnidirectionalStream(): Promise<WritableStream<Uint8Array>> {
		const out = pipe();
		this.peer.#uni.enqueue(out.readable);
		return out.writable;
	}

	close(): void {
		if (this.#isClosed) return;
		this.#isClosed = true;
		this.#closeResolve({ closeCode: 0, reason: "closed" });
		this.#bidi.close();
		this.#uni.close();
		this.peer.close();
	}
}

/** [client side, server side]; both report `protocol` as negotiated. */
export function fakeTransportPair(protocol = "moq-lite-03"): [WebTransport, WebTransport] {
	const a = new Side(protocol);
	const b = new Side(protocol);
	a.peer = b;
	b.peer = a;
	return [a as unknown as WebTransport, b as unknown as WebTransport];
}
