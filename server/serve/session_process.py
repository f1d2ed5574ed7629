"""One served session in its own OS process: ``python -m server.serve.session_process SPEC``.

Runs the same body as ``upcast up`` (server/serve/session_body.py) and writes
its state to the spec's status file, where the supervisor reads it for
``/sessions`` and ``/metrics``. Exits 1 when the session fails (the game
died, the relay never took the broadcast): the supervisor restarts it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from server.ops.logging_setup import install_redaction
from server.serve.session_body import LiveSession, SessionPlan, run_game_session
from server.serve.spec import SessionSpec
from server.stack.local import SourceStopped

log = logging.getLogger(__name__)


# The process's exit code when its source ended for good (an X11 application exited
# and app_exit is "stop"): the supervisor leaves it ended instead of restarting it.
SOURCE_ENDED_CODE = 3


def write_status(path: Path, state: str, live: LiveSession | None = None) -> None:
    record: dict[str, Any] = {"pid": os.getpid(), "state": state, "updated": time.time()}
    if live is not None:
        stack, status = live.stack, live.status.record()
        record.update(
            worker_pid=None if stack.worker is None else stack.worker.pid,
            game_pid=None if stack.game is None else stack.game.pid,
            worker_restarts=stack.worker_restarts,
            fps=status.fps,
            frames=status.frames,
            upscaler=status.upscaler,
            scale=status.scale,
            frame_generation=status.frame_generation,
            encoded=status.encoded,
            frame_rate=status.frame_rate,
            quality=status.quality,
            quality_reason=status.quality_reason,
            quality_at_floor=status.quality_at_floor,
            quality_cores_short=status.quality_cores_short,
            expected_psnr_db=status.expected_psnr_db,
            metrics_port=live.metrics_port,
        )
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record))
    os.replace(tmp, path)  # readers never see half a record


async def _run(spec: SessionSpec) -> int:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    plan = SessionPlan(
        config=spec.config,
        stream=spec.stream,
        relay_url=spec.relay_url,
        token=spec.token,
        metrics_port=spec.metrics_port,
        cert_hash_hex=spec.cert_hash_hex,
        frame_tap_port=spec.frame_tap_port,
        frame_tap_host=spec.frame_tap_host,
    )
    running: list[LiveSession] = []

    def up(live: LiveSession) -> None:
        running.append(live)
        write_status(spec.status_path, "up", live)

    def reconnect() -> None:
        if running:
            running[0].session.reconnect()

    # The supervisor sends SIGUSR1 after it restarted the relay: reconnect now rather
    # than after the dead connection's idle timeout.
    loop.add_signal_handler(signal.SIGUSR1, reconnect)
    write_status(spec.status_path, "starting")
    try:
        await run_game_session(
            plan,
            stop,
            on_up=up,
            on_tick=lambda live: write_status(spec.status_path, "up", live),
        )
    except SourceStopped as exc:
        log.warning("session %s: %s", spec.stream.broadcast, exc)
        write_status(spec.status_path, "ended")
        return SOURCE_ENDED_CODE
    except (RuntimeError, TimeoutError) as exc:
        log.error("session %s failed: %s", spec.stream.broadcast, exc)
        write_status(spec.status_path, "failed")
        return 1
    write_status(spec.status_path, "stopped")
    return 0


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m server.serve.session_process SPEC.json", file=sys.stderr)
        return 2
    spec = SessionSpec.model_validate_json(Path(argv[0]).read_text())
    logging.basicConfig(
        level=logging.INFO,
        format=f"%(asctime)s %(levelname)s [{spec.stream.broadcast}] %(name)s: %(message)s",
    )
    install_redaction()
    logging.getLogger("quic").setLevel(logging.WARNING)
    from server.ops.event_loop import install_uvloop

    install_uvloop()
    return asyncio.run(_run(spec))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
