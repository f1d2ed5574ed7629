"""A spectator's rendition choice (client_web/src/abr.ts), in node (issue 44).

The rules one at a time, fed by hand: the start on the cheapest rung, down at once on a
skipped group, a growing delay, low delivered fps, a stall or a decoder falling behind;
up only after a hold of stable playback, with a throughput estimate twice the next
rung's cap (or as a probe when nothing was measured); the hold doubling (bounded) after
an up-switch that failed soon; a catalog with one rendition never switching; garbage
inputs ignored; a page without a token never asking for a keyframe, and fetching the
latest group again when none comes. Then whole runs over a simulated link
(client_web/test/abr_check.ts): 300 kbit/s ends on the lowest rung and stays (at most a
probe every two minutes when nothing says otherwise), 4 Mbit/s at 60 ms with 1 % loss
shows a picture within 1 s and moves up once, a link that falls from 4 Mbit/s to
500 kbit/s goes down within a second and a half, one that gets better is found."""

from __future__ import annotations

from pathlib import Path

from tests.test_encode_catalog import NEEDS_NODE, run_in_node

CLIENT = Path(__file__).resolve().parents[1] / "client_web"

pytestmark = NEEDS_NODE


def test_spectator_rendition_choice(tmp_path: Path) -> None:
    out = run_in_node(tmp_path, CLIENT / "test" / "abr_check.ts")
    print(out["figures"])
    assert out["failures"] == []
    assert out["figures"]["link_300k"]["final"] == "video.320x180"
    assert out["figures"]["link_4m_lossy"]["final"] == "video.640x360"
