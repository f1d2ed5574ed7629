// The two numbers of a CMAF media fragment (moof+mdat) the player counts with:
// `mfhd` sequence_number (the encoder numbers its fragments 1, 2, 3...: a jump is a
// lost frame) and `tfdt` baseMediaDecodeTime (the encoder's pts, in the init segment's
// timescale). Why our own reader: @moq/hang's CMAF helpers do not expose mfhd, and
// these two boxes are a few fixed fields (ISO/IEC 14496-12 8.8.5, 8.8.12).

export interface FragmentHeader {
	/** mfhd sequence_number. */
	sequence: number;
	/** tfdt baseMediaDecodeTime of the first traf, in the track's timescale. */
	decodeTime: number;
}

/** The header of one moof+mdat, or undefined when it has no moof/mfhd/tfdt. */
export function readFragmentHeader(data: Uint8Array): FragmentHeader | undefined {
	const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
	const moof = findBox(view, 0, view.byteLength, "moof");
	if (!moof) return undefined;
	const mfhd = findBox(view, moof.body, moof.end, "mfhd");
	const traf = findBox(view, moof.body, moof.end, "traf");
	const tfdt = traf && findBox(view, traf.body, traf.end, "tfdt");
	if (!mfhd || !tfdt || mfhd.end - mfhd.body < 8) return undefined;
	const sequence = view.getUint32(mfhd.body + 4); // after version + flags
	const version = view.getUint8(tfdt.body);
	let decodeTime: number;
	if (version === 1) {
		if (tfdt.end - tfdt.body < 12) return undefined;
		// 64 bits; a Number holds it exactly up to 2^53 us (285 years).
		decodeTime = view.getUint32(tfdt.body + 4) * 2 ** 32 + view.getUint32(tfdt.body + 8);
	} else {
		if (tfdt.end - tfdt.body < 8) return undefined;
		decodeTime = view.getUint32(tfdt.body + 4);
	}
	return { sequence, decodeTime };
}

interface Box {
	/** First byte after the box header. */
	body: number;
	end: number;
}

function findBox(view: DataView, start: number, end: number, type: string): Box | undefined {
	let at = start;
	while (at + 8 <= end) {
		let size = view.getUint32(at);
		let header = 8;
		if (size === 1) {
			if (at + 16 > end) return undefined;
			size = view.getUint32(at + 8) * 2 ** 32 + view.getUint32(at + 12);
			header = 16;
		} else if (size === 0) {
			size = end - at; // to the end of the enclosing space
		}
		if (size < header || at + size > end) return undefined;
		const name = String.fromCharCode(view.getUint8(at + 4), view.getUint8(at + 5), view.getUint8(at + 6), view.getUint8(at + 7));
		if (name === type) return { body: at + header, end: at + size };
		at += size;
	}
	return undefined;
}
