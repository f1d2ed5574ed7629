"""A PulseAudio server of the session's own, with one null sink, for the application's
sound (issue 24): the program plays into the sink, the session records its monitor
(server/session/pulse_monitor.py) and streams it as the audio track.

One server per session, on a Unix socket in the session's own folder, anonymous
(only processes that can reach the folder can connect) and without D-Bus or the
user's configuration (``-n``: nothing loaded but what is named here), so two
sessions side by side never hear each other and nothing of the host's sound leaks
in. If ``pulseaudio`` is not installed the application runs without sound
(SDL_AUDIODRIVER=dummy) and the log says so.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import time
from pathlib import Path

from server.ops import orphan_guard

log = logging.getLogger(__name__)

SINK = "upcast"
MONITOR = f"{SINK}.monitor"
SAMPLE_RATE = 48_000
START_TIMEOUT_S = 10.0


class PulseServer:
    def __init__(self, process: subprocess.Popen[bytes], directory: Path) -> None:
        self._process = process
        self.directory = directory

    @property
    def socket(self) -> Path:
        return self.directory / "native"

    @property
    def address(self) -> str:
        return f"unix:{self.socket}"

    @classmethod
    def start(cls, directory: Path) -> PulseServer | None:
        """A server on ``directory``/native with the null sink; None (and a warning)
        where pulseaudio is not installed or does not come up."""
        exe = shutil.which("pulseaudio")
        if exe is None:
            log.warning(
                "pulseaudio is not installed (Debian: pulseaudio pulseaudio-utils): "
                "the application runs without sound"
            )
            return None
        directory.mkdir(parents=True, exist_ok=True)
        orphan_guard.watch_path(directory)  # removed (and the server ended) should we die
        env = {
            "HOME": str(directory),
            "XDG_RUNTIME_DIR": str(directory),
            "PULSE_RUNTIME_PATH": str(directory),
            "PATH": "/usr/bin:/bin",
        }
        args = [
            exe, "--daemonize=no", "--exit-idle-time=-1", "-n", "--use-pid-file=no",
            "--disable-shm=yes", "--log-target=stderr", "--log-level=error",
            f"--load=module-native-protocol-unix socket={directory / 'native'} auth-anonymous=1",
            f"--load=module-null-sink sink_name={SINK} rate={SAMPLE_RATE} channels=1",
        ]  # fmt: skip
        log_file = (directory / "pulseaudio.log").open("wb")
        process = subprocess.Popen(
            args, env=env, stdin=subprocess.DEVNULL, stdout=log_file, stderr=log_file,
            start_new_session=True,
        )  # fmt: skip
        log_file.close()
        orphan_guard.watch_process(process.pid, group=True)
        server = cls(process, directory)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not server.socket.exists():
            if process.poll() is not None or time.monotonic() > deadline:
                tail = (directory / "pulseaudio.log").read_text(errors="replace")[-500:]
                server.close()
                log.warning("pulseaudio did not start (%s): no sound", tail.strip() or "no output")
                return None
            time.sleep(0.02)
        log.info("sound: PulseAudio on %s, null sink %s", server.address, SINK)
        return server

    def app_env(self) -> dict[str, str]:
        """What the application needs to play into the sink (SDL, OpenAL and libpulse
        clients all read PULSE_SERVER)."""
        return {
            "PULSE_SERVER": self.address,
            "PULSE_SINK": SINK,
            "SDL_AUDIODRIVER": "pulseaudio",
            "ALSOFT_DRIVERS": "pulse",
        }

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(3)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait(3)
        orphan_guard.forget_process(self._process.pid)
        shutil.rmtree(self.directory, ignore_errors=True)
        orphan_guard.forget_path(self.directory)
