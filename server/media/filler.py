"""H.264 filler data: bytes a decoder reads past, to make a frame as large as asked.

The session probes its viewer's link with padding (server/session/link_probe.py):
for a fraction of a second each frame is made at least a given size, so the path
carries a known rate whether or not the encoder has that much to say. The padding
rides inside the frame as a filler-data NAL unit (type 12, ITU-T H.264 7.3.2.7:
0xFF bytes and the RBSP stop bit), which every decoder discards: the picture is the
same, no new track or relay path is needed, and any MoQ player that decodes the
video track (``@moq/watch`` included) plays it unchanged.
"""

from __future__ import annotations

import struct

NAL_FILLER = 12
# A length-prefixed (AVCC, 4-byte) NAL unit of type 12 with no 0xFF byte at all:
# the length, the header and the RBSP trailing byte.
MIN_FILLER_BYTES = 4 + 1 + 1


def filler_nal(total_bytes: int) -> bytes:
    """An AVCC filler NAL unit of exactly ``total_bytes`` (at least
    ``MIN_FILLER_BYTES``) to append to an access unit."""
    if total_bytes < MIN_FILLER_BYTES:
        raise ValueError(f"a filler NAL unit takes at least {MIN_FILLER_BYTES} bytes")
    body = total_bytes - 4
    # 0xFF never forms a start code or needs emulation prevention; 0x80 ends the RBSP.
    return struct.pack(">IB", body, NAL_FILLER) + b"\xff" * (body - 2) + b"\x80"


def pad_sample(sample: bytes, at_least: int) -> bytes:
    """``sample`` (an AVCC access unit) with filler appended so it is at least
    ``at_least`` bytes, or unchanged where it is already (or too nearly) that big."""
    missing = at_least - len(sample)
    if missing < MIN_FILLER_BYTES:
        return sample
    return sample + filler_nal(missing)
