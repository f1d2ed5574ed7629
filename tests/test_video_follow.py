"""How far the player's sound waits for its picture (client_web/src/video_follow.ts),
in node.

A viewer that joins mid-stream catches up on the relay's cached group: each frame it
shows is less late than the one before. The sound follows the picture only once the
picture has been within the hold for a second; following at once moved the sound later
through the catch-up frames' offsets, each move as much silence (the likely cause of the
e2e join test's 0.4 s of silence in fresh CI runs)."""

from __future__ import annotations

from pathlib import Path

from tests.test_encode_catalog import NEEDS_NODE, run_in_node

CLIENT = Path(__file__).resolve().parents[1] / "client_web"

pytestmark = NEEDS_NODE


def test_a_joining_viewer_hears_one_move_of_the_sound_not_one_per_catch_up_frame(
    tmp_path: Path,
) -> None:
    out = run_in_node(tmp_path, CLIENT / "test" / "follow_check.ts")
    print(out["figures"])
    assert out["failures"] == []
