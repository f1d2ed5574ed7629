// A small picture of what the canvas shows, for the benchmarks and tests that compare
// it with the frame the server sent: the sums of each 4x4 block of pixels, per colour.
// Reading the canvas back and summing it takes a few milliseconds; a PNG snapshot
// (toDataURL) held the page's main thread for tens, which a benchmark taking one every
// second measured in its own latency figures.

export const THUMB_FACTOR = 4;
const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

export interface CanvasThumbnail {
	factor: number;
	rows: number;
	cols: number;
	/** The byte order of `sums` (the platform's). */
	littleEndian: boolean;
	/** rows x cols x 3 block sums (RGB), uint16, base64. */
	sums: string;
}

export function canvasThumbnail(canvas: HTMLCanvasElement): CanvasThumbnail {
	const f = THUMB_FACTOR;
	const rows = Math.floor(canvas.height / f);
	const cols = Math.floor(canvas.width / f);
	const ctx = canvas.getContext("2d");
	if (!ctx || rows === 0 || cols === 0) return { factor: f, rows: 0, cols: 0, littleEndian: LITTLE_ENDIAN, sums: "" };
	const rgba = ctx.getImageData(0, 0, cols * f, rows * f).data;
	const stride = cols * f * 4;
	// 16 x 255 fits 16 bits: the sums are exact, the reader divides. Rows are read in
	// memory order (a block-by-block walk was several times slower).
	const sums = new Uint16Array(rows * cols * 3);
	for (let r = 0; r < rows; r++) {
		const base = r * cols * 3;
		for (let y = 0; y < f; y++) {
			let i = (r * f + y) * stride;
			for (let c = 0, o = base; c < cols; c++, o += 3) {
				let red = 0;
				let green = 0;
				let blue = 0;
				for (let x = 0; x < f; x++, i += 4) {
					red += rgba[i];
					green += rgba[i + 1];
					blue += rgba[i + 2];
				}
				sums[o] += red;
				sums[o + 1] += green;
				sums[o + 2] += blue;
			}
		}
	}
	const bytes = new Uint8Array(sums.buffer);
	return { factor: f, rows, cols, littleEndian: LITTLE_ENDIAN, sums: base64(bytes) };
}

function base64(bytes: Uint8Array): string {
	let text = "";
	const chunk = 0x2000; // String.fromCharCode takes its arguments on the stack
	for (let i = 0; i < bytes.length; i += chunk) {
		text += String.fromCharCode.apply(null, bytes.subarray(i, i + chunk) as unknown as number[]);
	}
	return btoa(text);
}
