"""The supervisor of ``upcast serve``: one OS process per session, restarted when it dies.

Each session process runs in its own process group, so when one is killed
(even with SIGKILL, when no cleanup of its own runs) the supervisor ends the
game and worker it left behind and removes its rings and sockets, then starts
it again after a backoff (1 s, doubling to 30 s; back to 1 s once a start
stayed up for a minute). The other sessions share nothing with it but the
relay, so they never notice. Should the supervisor itself die, SIGKILL included, its
reaper (server/ops/orphan_guard.py) ends every session's group and removes its files.

Sessions start through admission (server/serve/admission.py): with ``refuse`` or
``queue`` one after the other, and none while a running session's adaptive quality
says the host cannot hold even its cheapest setting; ``admit`` starts them all at once.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.frames.frame import Size
from server.ops import orphan_guard
from server.ops.cpu_shares import CpuShares, shares_for
from server.serve import share_planner
from server.serve.admission import Admission
from server.serve.session_process import SOURCE_ENDED_CODE
from server.serve.spec import SessionSpec
from server.serve.tokens import TokenMinter, no_token
from server.session.quality.peers import HOST_FILE_ENV, PeerRow, write_host_file
from server.stack.local import SessionConfig, session_files
from server.stream_config import StreamConfig

log = logging.getLogger(__name__)

BACKOFF_MIN_S = 1.0
BACKOFF_MAX_S = 30.0
STABLE_AFTER_S = 60.0
STATUS_STALE_S = 5.0  # a status file older than this: the session is hung or gone
STOP_TIMEOUT_S = 15.0


@dataclass
class ServedSession:
    index: int
    config: SessionConfig  # its name is replaced by a fresh one at every start
    stream: StreamConfig
    metrics_port: int
    status_path: Path
    frame_tap_port: int = 0  # 0: off
    frame_tap_host: str = "127.0.0.1"
    proc: subprocess.Popen[bytes] | None = None
    name: str = ""  # the current start's session name (rings, sockets)
    restarts: int = 0
    started_at: float = 0.0
    next_start_at: float | None = None  # set while waiting out a backoff
    backoff_s: float = BACKOFF_MIN_S
    last_exit: int | None = None
    ended: bool = False  # its application exited for good (source x11, app_exit stop)
    # Admission: "pending" until its turn, then "admitted", "refused" or "queued".
    admission: str = "pending"
    admission_reason: str | None = None
    # Its CPU weight's factor over its base (share_planner.py) and why it was last moved.
    share_boost: float = 1.0
    share_reason: str | None = None
    steady_since: float = 0.0  # its start or its worker's last restart (monotonic)
    worker_restarts_seen: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def broadcast(self) -> str:
        return self.stream.broadcast

    def status(self) -> dict[str, Any]:
        """The session process's own report (empty when there is none yet)."""
        try:
            record: dict[str, Any] = json.loads(self.status_path.read_text())
        except (OSError, ValueError):
            return {}
        return record


class Supervisor:
    def __init__(
        self,
        sessions: list[ServedSession],
        *,
        relay_url: str,
        cert_hash_hex: str | None = None,
        token_for: TokenMinter = no_token,
        admission: Admission | None = None,
        cpu: CpuShares | None = None,
    ) -> None:
        """``cpu``: the sessions' CPU shares (cgroups); None: not enforced."""
        self.sessions = sessions
        self.admission = admission if admission is not None else Admission("admit")
        self.cpu = cpu
        self._shares_at = -math.inf  # when share_planner last ran
        if cpu is not None:
            for path in cpu.paths:  # removed by the reaper should we die (SIGKILL)
                orphan_guard.watch_path(path)
        self.relay_url = relay_url
        self.cert_hash_hex = cert_hash_hex
        self.token_for = token_for
        self._dir = Path(tempfile.mkdtemp(prefix="upcast-serve-"))
        self.host_path = self._dir / "host.json"
        self._generation = 0

    # -- lifecycle ------------------------------------------------------------------------

    def start_all(self) -> None:
        """Start the sessions admission lets start now (all of them under ``admit``);
        check() starts the others when their turn comes."""
        self._admit(time.monotonic())

    def _admit(self, now: float) -> None:
        for s in self.sessions:
            if s.admission not in ("pending", "queued"):
                continue
            if s.proc is not None or s.ended or s.next_start_at is not None:
                s.admission = "admitted"  # started already (a restart is no new admission)
                continue
            verdict = self.admission.decide(self._admission_rows(now), now)
            if verdict.action == "wait":
                return  # the next one waits its turn: sessions start in order
            if verdict.action == "start":
                if s.admission == "queued" and not self.admission.queue_may_start(now):
                    return
                s.admission, s.admission_reason = "admitted", None
                self._start(s)
                continue  # the next one's verdict sees this one (settling, if auto)
            if s.admission != verdict.action:
                log.warning(
                    "session %d (%s) %s: %s",
                    s.index,
                    s.broadcast,
                    "refused" if verdict.action == "refuse" else "queued",
                    verdict.reason,
                )
            s.admission = "refused" if verdict.action == "refuse" else "queued"
            s.admission_reason = verdict.reason
            if verdict.action == "queue":
                return  # the queue keeps its order

    def _admission_rows(self, now: float) -> list[dict[str, Any]]:
        rows = []
        for s in self.sessions:
            if s.admission != "admitted" or s.proc is None:
                continue
            status = s.status()
            state = self.state_of(s, status)
            rows.append(
                {
                    "broadcast": s.broadcast,
                    "state": state,
                    # Known from its config before its first status report.
                    "quality": status.get("quality", s.stream.quality),
                    "quality_at_floor": status.get("quality_at_floor"),
                    "fps": status.get("fps", 0.0),
                    "target_fps": s.config.fps,
                    "frame_rate": status.get("frame_rate"),
                    "up_for_s": now - s.started_at if state == "up" else 0.0,
                }
            )
        return rows

    def _start(self, s: ServedSession) -> None:
        self._generation += 1
        s.name = f"upcast-serve-{os.getpid()}-{s.index}-{self._generation}"
        spec = SessionSpec(
            index=s.index,
            config=s.config.model_copy(update={"name": s.name}),
            stream=s.stream,
            relay_url=self.relay_url,
            token=self.token_for(s.broadcast),
            cert_hash_hex=self.cert_hash_hex,
            metrics_port=s.metrics_port,
            status_path=s.status_path,
            frame_tap_port=s.frame_tap_port,
            frame_tap_host=s.frame_tap_host,
        )
        spec_path = self._dir / f"session-{s.index}.json"
        spec_path.write_text(spec.model_dump_json())
        s.status_path.unlink(missing_ok=True)
        # Its own process group: the game and worker it starts go with it (see _reap).
        # Should the supervisor die without stopping it (SIGKILL), its reaper ends the
        # group and removes the files (the session's own reaper does too).
        for path in session_files(s.name):
            orphan_guard.watch_path(path)
        # Where the host's other sessions say what they wait for (peers.py).
        env = {**os.environ, HOST_FILE_ENV: str(self.host_path)}
        env[HOST_FILE_ENV + "_INDEX"] = str(s.index)
        s.proc = subprocess.Popen(
            [sys.executable, "-m", "server.serve.session_process", str(spec_path)],
            start_new_session=True,
            env=env,
        )
        orphan_guard.watch_process(s.proc.pid, group=True)
        if self.cpu is not None:
            # Placed before it can start its game and worker (it imports for a while
            # first): they inherit the group.
            # A fresh process starts from its base weight (a boost was its last life's).
            s.share_boost, s.share_reason = 1.0, None
            s.steady_since, s.worker_restarts_seen = time.monotonic(), 0
            self.cpu.place(_cpu_group(s), s.proc.pid, _base_shares(s))
        s.started_at = time.monotonic()
        s.next_start_at = None
        s.admission, s.admission_reason = "admitted", None
        log.info("session %d (%s): pid %d", s.index, s.broadcast, s.proc.pid)

    def check(self) -> None:
        """Notice dead session processes and restart them after their backoff."""
        now = time.monotonic()
        for s in self.sessions:
            if s.proc is not None and s.proc.poll() is not None:
                s.last_exit = s.proc.returncode
                self._reap(s)
                s.proc = None
                if s.last_exit == SOURCE_ENDED_CODE:
                    # Its application exited and the session's policy is to stop
                    # (app_exit "stop"; "restart" restarts it inside the session).
                    s.ended = True
                    log.info(
                        "session %d (%s): its application exited; not restarted (app_exit stop)",
                        s.index,
                        s.broadcast,
                    )
                    continue
                if now - s.started_at >= STABLE_AFTER_S:
                    s.backoff_s = BACKOFF_MIN_S
                s.restarts += 1
                s.next_start_at = now + s.backoff_s
                log.warning(
                    "session %d (%s) exited with code %s; restart #%d in %.0f s",
                    s.index, s.broadcast, s.last_exit, s.restarts, s.backoff_s,
                )  # fmt: skip
                s.backoff_s = min(BACKOFF_MAX_S, s.backoff_s * 2)
            elif s.proc is None and s.next_start_at is not None and now >= s.next_start_at:
                self._start(s)
        self._admit(now)
        self._move_shares(now)
        self._tell_peers()

    def _tell_peers(self) -> None:
        """The host file: which running sessions wait for cores to raise their frame rate,
        at what fraction of their target, short of how many idle cores (the others'
        controllers leave them the idle cores, and free some when they can)."""
        rows = []
        for s in self.sessions:
            if s.proc is None or s.proc.poll() is not None:
                continue
            status = s.status()
            rate, short = status.get("frame_rate"), status.get("quality_cores_short")
            waiting = isinstance(rate, int | float) and isinstance(short, int | float)
            if waiting and s.config.fps > 0:
                rows.append(PeerRow(s.index, float(rate) / s.config.fps, float(short)))  # type: ignore[arg-type]
            else:
                rows.append(PeerRow(s.index, None, None))
        try:
            write_host_file(self.host_path, rows)
        except OSError as exc:  # a full or vanished temp dir: the sessions read nothing
            log.debug("host file not written: %s", exc)

    def _move_shares(self, now: float) -> None:
        """Every PERIOD_S, the weights share_planner gives the running sessions."""
        if (
            self.cpu is None
            or not self.cpu.available
            or now - self._shares_at < share_planner.PERIOD_S
        ):
            return
        self._shares_at = now
        by_group: dict[str, ServedSession] = {}
        rows: list[share_planner.ShareInput] = []
        for s in self.sessions:
            if s.proc is None or s.proc.poll() is not None:
                continue
            status = s.status()
            fps = status.get("fps")
            restarts = status.get("worker_restarts", 0)
            if isinstance(restarts, int) and restarts != s.worker_restarts_seen:
                s.worker_restarts_seen, s.steady_since = restarts, now
            group = _cpu_group(s)
            by_group[group] = s
            rows.append(
                share_planner.ShareInput(
                    group=group,
                    label=f"session {s.index} ({s.broadcast})",
                    base=_base_shares(s),
                    boost=s.share_boost,
                    up=self.state_of(s, status) == "up",
                    fps=float(fps) if isinstance(fps, int | float) else None,
                    # The rate it runs at now: a session that lowered its frame rate is
                    # judged against that, not the configured one.
                    target_fps=float(rate)
                    if isinstance(rate := status.get("frame_rate"), int | float) and rate > 0
                    else s.config.fps,
                    can_trade=status.get("quality") == "auto"
                    and status.get("quality_at_floor") is not True,
                    steady_s=now - s.steady_since,
                )
            )
        for change in share_planner.plan(rows):
            s = by_group[change.group]
            if self.cpu.set_shares(change.group, change.shares):
                log.info(
                    "cpu shares: %s -> %d (x%.2f of its base)",
                    change.reason, change.shares, change.boost,
                )  # fmt: skip
                s.share_boost, s.share_reason = change.boost, change.reason

    def relay_restarted(self) -> None:
        """Tell every session to reconnect at once (SIGUSR1, see session_process.py)."""
        for s in self.sessions:
            # A status file exists only once the process handles SIGUSR1 (else it would die).
            if s.proc is not None and s.proc.poll() is None and s.status():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(s.proc.pid, signal.SIGUSR1)

    def _reap(self, s: ServedSession) -> None:
        """End what a dead session process left behind: its game, its worker, its files."""
        assert s.proc is not None
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(s.proc.pid, signal.SIGKILL)
        orphan_guard.forget_process(s.proc.pid)
        for path in session_files(s.name):
            path.unlink(missing_ok=True)
            orphan_guard.forget_path(path)

    def stop_all(self) -> None:
        running = [s for s in self.sessions if s.proc is not None and s.proc.poll() is None]
        for s in running:
            assert s.proc is not None
            s.proc.terminate()
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for s in running:
            assert s.proc is not None
            try:
                s.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("session %d did not stop in time: killed", s.index)
        for s in self.sessions:
            if s.proc is not None:
                self._reap(s)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    s.proc.wait(5)
            s.proc = None
            s.next_start_at = None
        if self.cpu is not None:
            self.cpu.close()
        for path in self._dir.iterdir():
            path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            self._dir.rmdir()

    # -- reporting ------------------------------------------------------------------------

    def state_of(self, s: ServedSession, status: dict[str, Any]) -> str:
        if s.proc is None:
            if s.ended:
                return "ended"
            if s.admission == "pending":
                return "waiting"
            if s.admission in ("refused", "queued"):
                return s.admission
            return "restarting" if s.next_start_at is not None else "stopped"
        state = str(status.get("state", "starting"))
        if state == "up" and time.time() - float(status.get("updated", 0)) > STATUS_STALE_S:
            return "stalled"
        return state

    def snapshot(self) -> list[dict[str, Any]]:
        """One dict per session: what ``GET /sessions`` answers."""
        out = []
        for s in self.sessions:
            status = s.status() if s.proc is not None else {}
            out.append(
                {
                    "index": s.index,
                    "name": s.name,
                    "broadcast": s.broadcast,
                    "pid": None if s.proc is None else s.proc.pid,
                    "state": self.state_of(s, status),
                    "restarts": s.restarts,
                    "last_exit": s.last_exit,
                    "worker_pid": status.get("worker_pid"),
                    "game_pid": status.get("game_pid"),
                    "worker_restarts": status.get("worker_restarts", 0),
                    "fps": status.get("fps", 0.0),
                    "frames": status.get("frames", 0),
                    # When the session counted ``frames`` (wall clock): rates from these
                    # two are exact, whenever /sessions is read.
                    "frames_at": status.get("updated"),
                    "upscaler": status.get("upscaler", s.config.upscaler),
                    "scale": status.get("scale", round(s.config.scale, 3)),
                    "frame_generation": status.get("frame_generation"),
                    "encoded": status.get("encoded"),
                    # Frames per second the game renders now (adaptive quality may lower
                    # it below target_fps, the configured rate, when nothing cheaper holds).
                    "frame_rate": status.get("frame_rate", s.config.fps),
                    # Adaptive quality: auto or fixed, why this setting, and the picture
                    # the speed-against-error table expects of it.
                    "quality": status.get("quality"),
                    "quality_reason": status.get("quality_reason"),
                    "quality_at_floor": status.get("quality_at_floor"),
                    # Below its rate, waiting for idle cores to raise it: the host's other
                    # sessions hold their step ups (server/session/quality/peers.py).
                    "quality_cores_short": status.get("quality_cores_short"),
                    "expected_psnr_db": status.get("expected_psnr_db"),
                    # Why it was not started (refused or queued), else None.
                    "admission_reason": s.admission_reason,
                    # Its cgroup's CPU weight and the CPU seconds it used (None: not
                    # enforced here, see cpu_shares_reason in the relay row).
                    "cpu_shares": None if self.cpu is None else self.cpu.shares(_cpu_group(s)),
                    # Why its weight was last moved from its base (None: never was).
                    "cpu_shares_reason": s.share_reason,
                    "cpu_seconds": _rounded(
                        None if self.cpu is None else self.cpu.cpu_seconds(_cpu_group(s))
                    ),
                    "target_fps": s.config.fps,
                    "metrics_port": status.get("metrics_port", 0),
                }
            )
        return out

    def all_up(self) -> bool:
        """Every session admission let start is up, and none waits for its turn."""
        return all(row["state"] in ("up", "refused", "queued") for row in self.snapshot())


def _base_shares(s: ServedSession) -> int:
    display = Size.parse(s.config.display_size)
    return shares_for(s.config.fps, display.width * display.height)


def _cpu_group(s: ServedSession) -> str:
    return f"session-{s.index}"


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 2)
