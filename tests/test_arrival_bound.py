"""The player's audio arrival bound (client_web/src/arrival_bound.ts) in node.

The sound's sync target covers the chunks' arrival offsets: the 95th percentile of
the last 3 s, except that the single worst burst of late chunks (one stall of the
page) does not count; two bursts move it as far as the smaller. Without that, one
220 ms stall held the sound 200 ms behind the picture for 3 s (the stall test in
tests/e2e/test_audio_e2e.py: |A/V| 100-150 ms on a freshly started page)."""

from __future__ import annotations

from pathlib import Path

from tests.test_encode_catalog import NEEDS_NODE, run_in_node

CLIENT = Path(__file__).resolve().parents[1] / "client_web"

pytestmark = NEEDS_NODE


def test_arrival_bound_ignores_one_stall_and_covers_repeated_ones(tmp_path: Path) -> None:
    out = run_in_node(tmp_path, CLIENT / "test" / "arrival_check.ts")
    print(out["bounds"])
    assert out["failures"] == []
