"""Where our relay's CPU goes: a py-spy profile over the measured window.

``py-spy record --format raw`` writes collapsed stacks (``frame;frame;... count``);
the leaf of each stack is the function that was running, so summing counts per leaf
gives each function's own time. py-spy leaves out idle samples (the event loop
waiting in epoll), so the counts are busy time; ``--nonblocking`` reads the relay's
memory without pausing it, and py-spy's own CPU is its process's, not the relay's.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.ops.process import stop_child

RATE_HZ = 100
TOP_FUNCTIONS = 15
FINISH_SLACK_S = 15.0  # py-spy writing its file after --duration ends


def find_py_spy() -> str | None:
    """py-spy on PATH, or next to this Python (a venv that is not activated)."""
    found = shutil.which("py-spy")
    if found is not None:
        return found
    beside = Path(sys.executable).parent / "py-spy"
    return str(beside) if beside.exists() else None


def leaf_counts(raw: str) -> Counter[str]:
    """Samples per leaf frame (``function (file:line)``), from collapsed stacks."""
    leaves: Counter[str] = Counter()
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if stack and count.isdigit():
            leaves[stack.rsplit(";", 1)[-1]] += int(count)
    return leaves


def own_time(raw: str, top: int = TOP_FUNCTIONS) -> tuple[int, list[tuple[str, int]]]:
    """Total samples and the ``top`` leaf functions by samples."""
    leaves = leaf_counts(raw)
    return sum(leaves.values()), leaves.most_common(top)


def own_time_by_file(raw: str, top: int = TOP_FUNCTIONS) -> list[tuple[str, int]]:
    """The ``top`` source files by own samples: aioquic, the relay, crypto, asyncio..."""
    files: Counter[str] = Counter()
    for leaf, count in leaf_counts(raw).items():
        inside = leaf.rpartition(" (")[2].rstrip(")")
        files[inside.rpartition(":")[0] or inside] += count
    return files.most_common(top)


@dataclass
class Profiler:
    """One py-spy run on ``pid``, started ``delay_s`` from now for ``duration_s``."""

    py_spy: str
    pid: int
    out: Path
    delay_s: float
    duration_s: int
    error: str | None = None
    _proc: subprocess.Popen[bytes] | None = None
    _timer: threading.Timer | None = field(default=None, repr=False)

    def start(self) -> None:
        self._timer = threading.Timer(self.delay_s, self._launch)
        self._timer.start()

    def _launch(self) -> None:
        argv = [self.py_spy, "record", "--pid", str(self.pid), "--duration", str(self.duration_s)]
        argv += ["--rate", str(RATE_HZ), "--format", "raw", "--function", "--nonblocking"]
        argv += ["--output", str(self.out)]
        try:
            self._proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        except OSError as exc:
            self.error = f"py-spy did not start: {exc}"

    def cancel(self) -> None:
        """Stop the profile early (the run it was for failed)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer.join()
        if self._proc is not None:
            stop_child(self._proc, 2.0)

    def finish(self) -> dict[str, Any]:
        """Wait for py-spy and summarize what it wrote (or why nothing)."""
        if self._timer is not None:
            self._timer.join()
        proc = self._proc
        if proc is not None:
            try:
                _, stderr = proc.communicate(timeout=self.duration_s + FINISH_SLACK_S)
            except subprocess.TimeoutExpired:
                stop_child(proc, 2.0)
                stderr = b""
            if proc.returncode != 0 and self.error is None:
                tail = stderr.decode(errors="replace").strip().splitlines()[-1:]
                self.error = f"py-spy exited with {proc.returncode}: {' '.join(tail)}"
        if self.error is None and not self.out.exists():
            self.error = "py-spy wrote no profile"
        if self.error is not None:
            return {"error": self.error}
        raw = self.out.read_text(errors="replace")
        samples, top = own_time(raw)
        expected = RATE_HZ * self.duration_s
        return {
            "file": str(self.out),
            "samples_busy": samples,
            "busy_percent_of_core": round(100.0 * samples / expected, 1) if expected else None,
            "top_own_time": [
                {
                    "function": name,
                    "samples": count,
                    "percent_of_busy": round(100.0 * count / samples, 1) if samples else 0.0,
                }
                for name, count in top
            ],
            "top_files_own_time": [
                {
                    "file": name,
                    "samples": count,
                    "percent_of_busy": round(100.0 * count / samples, 1) if samples else 0.0,
                }
                for name, count in own_time_by_file(raw)
            ],
        }
