"""The network emulator in a process of its own, for ``upcast bench network``.

The benchmark's process already runs the streaming session (its encoder, aioquic
and asyncio) and Playwright; an emulator thread there would wait for the GIL and
hold packets late (its ``release_late_ms`` showed p99 over 60 ms on a loaded
2-core machine), which the report would blame on the link. A spawned process
runs ``NetworkEmulator`` on its own event loop and answers a few commands over a
pipe: the port, ``stats()``, ``restart_schedule()``, stop. Same interface as
``EmulatorThread``.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
from multiprocessing.connection import Connection
from types import TracebackType
from typing import Any

from server.net import NetworkEmulator, Schedule, emulator_loop

START_TIMEOUT_S = 30.0
ANSWER_TIMEOUT_S = 10.0


def _serve(conn: Connection, kwargs: dict[str, Any]) -> None:
    async def main() -> None:
        emulator = await NetworkEmulator(**kwargs).start()
        conn.send(("port", emulator.port))
        loop = asyncio.get_running_loop()
        commands: asyncio.Queue[str] = asyncio.Queue()

        def readable() -> None:
            try:
                commands.put_nowait(conn.recv())
            except (EOFError, OSError):
                commands.put_nowait("stop")

        loop.add_reader(conn.fileno(), readable)
        try:
            while (command := await commands.get()) != "stop":
                if command == "stats":
                    conn.send(("stats", emulator.stats()))
                elif command == "restart":
                    emulator.restart_schedule()
                    conn.send(("restart", None))
        finally:
            loop.remove_reader(conn.fileno())
            await emulator.stop()
            with contextlib.suppress(OSError):
                conn.send(("stopped", None))

    with contextlib.suppress(KeyboardInterrupt), asyncio.Runner(loop_factory=emulator_loop) as run:
        run.run(main())


class EmulatorProcess:
    def __init__(
        self,
        *,
        listen: tuple[str, int],
        upstream: tuple[str, int],
        schedule: Schedule,
        tcp_passthrough: bool = False,
        seed: int = 0,
    ) -> None:
        self._kwargs: dict[str, Any] = {
            "listen": listen,
            "upstream": upstream,
            "schedule": schedule,
            "tcp_passthrough": tcp_passthrough,
            "seed": seed,
        }
        self._ctx = mp.get_context("spawn")
        self._conn: Connection | None = None
        self._proc: Any = None
        self.port = 0

    def start(self) -> EmulatorProcess:
        parent, child = self._ctx.Pipe()
        self._proc = self._ctx.Process(
            target=_serve, args=(child, self._kwargs), name="bench-netem", daemon=True
        )
        self._proc.start()
        child.close()
        self._conn = parent
        self.port = int(self._ask(None, "port", START_TIMEOUT_S))
        return self

    def _ask(self, command: str | None, answer: str, timeout_s: float = ANSWER_TIMEOUT_S) -> Any:
        conn = self._conn
        if conn is None:
            raise RuntimeError("the emulator process is not started")
        if command is not None:
            conn.send(command)
        if not conn.poll(timeout_s):
            raise RuntimeError(f"the emulator process did not answer {command or 'start'!r}")
        kind, value = conn.recv()
        if kind != answer:
            raise RuntimeError(f"the emulator process answered {kind!r}, not {answer!r}")
        return value

    def stats(self) -> dict[str, Any]:
        stats: dict[str, Any] = self._ask("stats", "stats")
        return stats

    def restart_schedule(self) -> None:
        self._ask("restart", "restart")

    def stop(self) -> None:
        conn, proc = self._conn, self._proc
        self._conn = None
        if conn is not None:
            with contextlib.suppress(OSError, EOFError):
                conn.send("stop")
                conn.poll(ANSWER_TIMEOUT_S)
            conn.close()
        if proc is not None:
            proc.join(ANSWER_TIMEOUT_S)
            if proc.is_alive():
                proc.terminate()
                proc.join(5.0)

    def __enter__(self) -> EmulatorProcess:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
