"""A session whose source is an X11 application: its end, restarts and neighbours.

Real processes (game with an Xvfb, worker) through LocalStack; small programs stand
in for games where only their lifetime matters (``sh``; ``xmessage`` of x11-utils
for a window).
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import numpy as np

from server.frames.ring import SHM_DIR
from server.frames.ring_frames import display_frame_of
from server.stack.local import LocalStack, SessionConfig, SourceStopped

RENDER = "160x90"
DISPLAY = "320x180"


def x11_config(app: str, **fields: object) -> SessionConfig:
    return SessionConfig(
        source="x11", app=app, render_size=RENDER, display_size=DISPLAY, fps=20, **fields
    )  # type: ignore[arg-type]


def wait_stopped(stack: LocalStack, timeout_s: float = 30.0) -> SourceStopped:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            stack.check_children()
        except SourceStopped as stopped:
            return stopped
        time.sleep(0.1)
    raise AssertionError(f"the session did not stop in {timeout_s:.0f} s")


def test_the_session_stops_with_the_application_and_says_its_code() -> None:
    with LocalStack(x11_config("sh -c 'sleep 1; exit 3'")) as stack:
        stopped = wait_stopped(stack)
    assert stopped.code == 3
    assert "application exited (code 3)" in str(stopped)


def test_restart_policy_restarts_then_gives_up_on_a_crash_loop() -> None:
    started = time.monotonic()
    with LocalStack(x11_config("sh -c 'sleep 0.5; exit 1'", app_exit="restart")) as stack:
        stopped = wait_stopped(stack, timeout_s=40.0)
    # three restarts of a 0.5 s program, then the session ends
    assert time.monotonic() - started >= 2.0
    assert stopped.code == 1


def test_a_missing_display_is_a_clear_start_failure() -> None:
    with LocalStack(x11_config("xmessage hi", x11_display=":97")) as stack:
        stopped = wait_stopped(stack)
    assert "could not start" in str(stopped)


def test_a_missing_program_is_a_clear_start_failure() -> None:
    with LocalStack(x11_config("/nonexistent/game --fast")) as stack:
        stopped = wait_stopped(stack)
    assert "could not start" in str(stopped)


def _frames(stack: LocalStack, n: int, timeout_s: float = 30.0) -> list[np.ndarray]:
    ring = stack.ring_u
    assert ring is not None
    ring.attach_as_consumer()
    got: list[np.ndarray] = []
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        stack.check_children()
        lease = ring.acquire_read(0.5, newest=True)
        if lease is None:
            continue
        with lease:
            got.append(display_frame_of(lease).color.copy())
    assert len(got) == n, f"{len(got)} frames in {timeout_s:.0f} s"
    return got


def test_two_sessions_stream_two_displays_side_by_side() -> None:
    """Each session has its own Xvfb and its own picture; stopping one leaves the other."""
    a = LocalStack(x11_config("xmessage -bg red -geometry 160x90+0+0 left"))
    b = LocalStack(x11_config("xmessage -bg blue -geometry 160x90+0+0 right"))
    with a, b:
        a.wait_ready()
        b.wait_ready()
        time.sleep(2.0)  # the windows map
        fa, fb = _frames(a, 3)[-1], _frames(b, 3)[-1]
        red = np.array([255, 0, 0])
        blue = np.array([0, 0, 255])

        def share(frame: np.ndarray, colour: np.ndarray) -> float:
            return float(np.mean(np.all(np.abs(frame.astype(int) - colour) < 40, axis=-1)))

        assert share(fa, red) > 0.3 and share(fa, blue) < 0.01
        assert share(fb, blue) > 0.3 and share(fb, red) < 0.01
        a.stop()
        _frames(b, 3)  # b streams on
    leftover = [p for p in os.listdir(SHM_DIR) if p.startswith(a.config.name)]
    assert leftover == []


def test_serve_leaves_a_session_whose_application_ended_and_restarts_a_crashed_one(
    tmp_path: Path,
) -> None:
    """upcast serve's supervisor: exit code SOURCE_ENDED_CODE (the application exited,
    app_exit stop) is final; any other exit is a crash and is restarted."""
    from server.serve.session_process import SOURCE_ENDED_CODE
    from server.serve.supervisor import ServedSession, Supervisor
    from server.stream_config import StreamConfig

    def served(index: int, code: int) -> ServedSession:
        s = ServedSession(
            index, SessionConfig(), StreamConfig(broadcast=f"b{index}"), 0, tmp_path / f"{index}"
        )
        s.proc = subprocess.Popen(["sh", "-c", f"exit {code}"], start_new_session=True)
        s.proc.wait()
        return s

    ended, crashed = served(1, SOURCE_ENDED_CODE), served(2, 1)
    supervisor = Supervisor([ended, crashed], relay_url="http://127.0.0.1:9/")
    try:
        supervisor.check()
        assert supervisor.state_of(ended, {}) == "ended" and ended.next_start_at is None
        assert supervisor.state_of(crashed, {}) == "restarting" and crashed.restarts == 1
    finally:
        supervisor.stop_all()
