"""What the other sessions on this host need: the arbiter between their controllers.

Each session's controller steps up into the host's idle cores, and on a host shared by
sessions the idle cores are what the others leave. Left alone, the session that looks
first takes them: one session spends them on a sharper picture while another runs below
its target frame rate, waiting for the same cores to raise it. The rate is worth more
than the picture (a frame rate below the target is a debt), so the host settles it:

- every session says in its status whether it is **waiting for cores**: below its target
  rate, with a rate step up that only the spare cores stop, and how many idle cores it
  lacks (``ControllerState.cores_short``);
- ``upcast serve``'s supervisor gathers those into one host file (``write_host_file``)
  each check and names it to its sessions in ``HOST_FILE_ENV``;
- each session reads the others' (``HostPeers.waiting``) into its measurement. While
  another session waits at a lower rate than its own for cores it could leave it (its
  idle share plus what a cheaper picture of its own would free), a session takes no step
  up that costs CPU, and, when the idle cores are not enough, steps its picture down by
  what the other lacks (the controller's ``_yield_to_peer``). The cores go to the
  session furthest below its target: max-min fairness over the fraction of the target
  each session shows. A claim nobody can meet holds nobody: no session gives its
  picture for nothing.

The file is JSON, written atomically; a reader ignores one older than ``STALE_S`` (a
supervisor that stopped writing says nothing any more), and any malformed content.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeGuard

HOST_FILE_ENV = "UPCAST_HOST_PEERS"
STALE_S = 5.0


@dataclass(frozen=True)
class PeerRow:
    index: int  # the session's 1-based index in serve
    waiting_rate: float | None  # its frame-rate fraction while it waits for cores, else None
    cores_short: float | None = None  # the idle cores it lacks while it waits


@dataclass(frozen=True)
class PeerWait:
    rate: float  # the waiting session's frame rate, a fraction of its target
    cores_short: float  # the idle cores its next rate up lacks


def write_host_file(path: Path, rows: Iterable[PeerRow], now_wall: float | None = None) -> None:
    record = {
        "written_at": time.time() if now_wall is None else now_wall,
        "sessions": [
            {"index": r.index, "waiting_rate": r.waiting_rate, "cores_short": r.cores_short}
            for r in rows
        ],
    }
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record))
    os.replace(tmp, path)  # a reader never sees half a file


def parse_peer_wait(text: str, own_index: int, now_wall: float) -> PeerWait | None:
    """The *other* session waiting for cores at the lowest frame-rate fraction (of those
    at that rate, the one short of the fewest cores); None when none waits, the record
    is stale, or it is not a host file."""
    try:
        record = json.loads(text)
        written = float(record["written_at"])
        rows = record["sessions"]
        if not isinstance(rows, list):
            return None
    except (ValueError, KeyError, TypeError):
        return None
    if not math.isfinite(written) or not 0 <= now_wall - written <= STALE_S:
        return None
    waits: list[PeerWait] = []
    for row in rows:
        if not isinstance(row, dict) or row.get("index") == own_index:
            continue
        rate, short = row.get("waiting_rate"), row.get("cores_short", 0.0)
        if not (_number(rate) and _number(short)):
            continue
        if 0 < rate <= 1 and short >= 0:
            waits.append(PeerWait(float(rate), float(short)))
    return min(waits, key=lambda w: (w.rate, w.cores_short)) if waits else None


def _number(value: object) -> TypeGuard[float]:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


class HostPeers:
    """Reads the host file the supervisor names (``HOST_FILE_ENV``); a session started
    alone (``upcast up``, a test) has none and always reads None."""

    def __init__(self, path: Path | None, own_index: int) -> None:
        self.path = path
        self.own_index = own_index

    @classmethod
    def from_environment(cls) -> HostPeers:
        path = os.environ.get(HOST_FILE_ENV)
        index = os.environ.get(HOST_FILE_ENV + "_INDEX", "0")
        return cls(Path(path) if path else None, int(index) if index.isdigit() else 0)

    def waiting(self) -> PeerWait | None:
        if self.path is None:
            return None
        try:
            text = self.path.read_text()
        except OSError:
            return None
        return parse_peer_wait(text, self.own_index, time.time())
