"""Adaptive quality in a session: the scene from the frames' cameras, the host's load,
and the adapter that applies decisions through the input router like a person's
control request (server/session/quality/adapter.py)."""

from __future__ import annotations

import asyncio
import math
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from server.frames.frame import Camera, FrameFlags, FrameMeta, Size
from server.frames.monitor import FrameRateMonitor
from server.game.input import InputMessage
from server.ops.host_load import HostLoad
from server.session.input_router import InputRouter
from server.session.quality.adapter import AUTO_SOURCE, SessionQuality, session_quality
from server.session.quality.controller import Decision, Measurement, QualityGoal
from server.session.quality.peers import HostPeers, PeerRow, write_host_file
from server.session.quality.scene import SceneTracker, camera_step
from server.session.runner import StreamSettings
from server.session.session_control import ControlResult


def _yaw(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    m = np.eye(4, dtype=np.float32)
    m[0, 0], m[0, 2], m[2, 0], m[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    return m


def _meta(deg_per_frame: float, frame: int, flags: FrameFlags = FrameFlags.NONE) -> FrameMeta:
    view, prev = _yaw(deg_per_frame * frame), _yaw(deg_per_frame * (frame - 1))
    eye = np.eye(4, dtype=np.float32)
    return FrameMeta(
        frame_id=frame, camera=Camera(view, eye, prev, eye, 0.1, 100.0, 60.0), flags=flags
    )


@pytest.mark.parametrize(("degrees", "expected"), [(0.0, "still"), (0.3, "slow"), (3.0, "fast")])
def test_the_scene_class_follows_the_camera(degrees: float, expected: str) -> None:
    tracker = SceneTracker()
    for i in range(1, 60):
        tracker.frame(_meta(degrees, i), i / 30)
    assert tracker.scene(59 / 30) == expected
    assert camera_step(_meta(degrees, 5)).degrees == pytest.approx(degrees, abs=1e-3)  # type: ignore[union-attr]


def test_cuts_colour_only_frames_and_broken_cameras() -> None:
    tracker = SceneTracker()
    for i in range(1, 60):
        flags = FrameFlags.RESET if i % 10 == 0 else FrameFlags.NONE
        tracker.frame(_meta(0.3, i, flags), i / 30)
    assert tracker.scene(59 / 30) == "cuts"
    colour_only = SceneTracker()
    broken = _meta(0.3, 3)
    broken.camera.view[0, 0] = np.nan
    for i in range(1, 30):
        colour_only.frame(_meta(0.3, i, FrameFlags.COLOR_ONLY), i / 30)
        colour_only.frame(broken, i / 30)
    assert camera_step(broken) is None
    assert colour_only.scene(1.0) == "unknown"


def test_host_load_reads_busy_cores_from_proc_stat(tmp_path: Path) -> None:
    stat = tmp_path / "stat"

    def write(user: int, idle: int) -> None:
        stat.write_text(
            f"cpu  {user} 0 0 {idle} 0 0 0 0 0 0\ncpu0 1 0 0 1 0 0 0 0 0 0\n"
            "cpu1 1 0 0 1 0 0 0 0 0 0\n"
        )

    write(100, 100)
    load = HostLoad(stat, cores=2)
    write(250, 150)  # 150 busy of 200 jiffies: 3/4 of 2 CPUs
    assert load.busy_cores() == pytest.approx(1.5)
    write(250, 150)  # no time passed: no reading
    assert load.busy_cores() is None
    assert HostLoad(tmp_path / "missing", cores=2).busy_cores() is None


class _Game:
    """The game's input socket: what the router sends it."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)

    def received(self) -> list[InputMessage]:
        out = []
        while True:
            try:
                out.append(InputMessage.model_validate_json(self.sock.recv(65536)))
            except BlockingIOError:
                return out


def _settings(**overrides: object) -> StreamSettings:
    fields: dict[str, object] = {
        "relay_url": "http://localhost:1/",
        "fps": 30.0,
        "upscaler": "bilinear",
        "scale": 2.0,
        "quality": "auto",
    }
    return StreamSettings(**(fields | overrides))  # type: ignore[arg-type]


def _adapter(tmp_path: Path, **overrides: object) -> tuple[SessionQuality, _Game, InputRouter]:
    game = _Game(tmp_path / "game.sock")
    router = InputRouter(
        game_input=tmp_path / "game.sock",
        worker_control=None,
        request_keyframe=lambda: None,
        max_frame_rate=30.0,
    )
    state: dict[str, str | float | bool] = {}
    monitor = FrameRateMonitor("session", 30.0)
    adapter = session_quality(_settings(**overrides), Size(1280, 720), router, monitor, state, None)
    router.on_control_outcome = adapter.control_outcome
    return adapter, game, router


def test_a_decision_reaches_the_game_as_a_control_request(tmp_path: Path) -> None:
    async def scenario() -> None:
        adapter, game, router = _adapter(tmp_path, upscaler="bilinear", scale=2.0)
        assert adapter.enabled and adapter.controller is not None
        results: list[ControlResult] = []
        router.on_control_result = results.append
        # A goal that forbids the current scale makes the controller move at once.
        goal = QualityGoal(target_fps=30.0, min_scale=3.0, max_scale=4.0, methods=("bilinear",))
        adapter.controller.set_goal(goal)
        decision = adapter.step(1000.0)
        assert decision is not None and decision.setting.scale >= 3.0
        sent = game.received()
        assert [m.render_scale for m in sent if m.render_scale is not None] == [
            decision.setting.scale
        ]
        assert results and results[-1].source == AUTO_SOURCE and results[-1].accepted
        assert adapter._state["quality"] == "auto"
        assert isinstance(adapter._state["quality_reason"], str)

    asyncio.run(scenario())


def test_a_refused_switch_is_set_back_in_the_controller_and_the_game(tmp_path: Path) -> None:
    """This session has no worker control socket: a method switch is refused, and the
    scale that would have gone with it is sent back to the game."""

    async def scenario() -> None:
        adapter, game, _router = _adapter(tmp_path, upscaler="bilinear", scale=2.0)
        assert adapter.controller is not None
        goal = QualityGoal(target_fps=30.0, min_scale=3.0, max_scale=4.0, methods=("bicubic",))
        adapter.controller.set_goal(goal)
        decision = adapter.step(1000.0)
        assert decision is not None and decision.setting.method == "bicubic"
        # Refused as a whole before anything was sent: the controller is back where it was.
        assert adapter.controller.setting == decision.previous
        assert "refused" in adapter.controller.state.reason
        assert all(m.render_scale in (None, 2.0) for m in game.received())

    asyncio.run(scenario())


def test_a_persons_request_pins_and_quality_fixed_stops_switching(tmp_path: Path) -> None:
    async def scenario() -> None:
        adapter, _game, router = _adapter(tmp_path)
        assert adapter.controller is not None
        router.handle("viewer", b'{"type":"control","seq":1,"scale":2.5}')
        assert adapter.controller.setting.scale == 2.5
        assert adapter.controller._pins.scale == 2.5
        router.handle("viewer", b'{"type":"control","seq":2,"quality":"auto","methods":["easu"]}')
        assert adapter.controller._pins.scale is None
        assert adapter.controller.goal.methods == ("easu",)
        router.handle("viewer", b'{"type":"control","seq":3,"quality":"fixed"}')
        assert not adapter.enabled
        assert adapter.step(1000.0) is None
        assert adapter._state["quality"] == "fixed"
        # A goal the router refuses changes nothing.
        router.handle("viewer", b'{"type":"control","seq":4,"methods":["nope"]}')
        router.handle("viewer", b'{"type":"control","seq":5,"min_scale":3,"max_scale":2}')
        assert adapter.controller.goal.methods == ("easu",)
        assert adapter.controller.goal.min_scale == 1.0

    asyncio.run(scenario())


def test_a_lower_frame_rate_reaches_the_game_and_a_persons_rate_pins(tmp_path: Path) -> None:
    async def scenario() -> None:
        adapter, game, router = _adapter(tmp_path)
        assert adapter.controller is not None
        rates: list[float] = []
        router.on_frame_rate = rates.append
        # A rate pinned to 20 fps' fraction: the controller conforms at once.
        adapter.controller.set_goal(QualityGoal(target_fps=30.0, methods=("bilinear",)))
        adapter.controller.pin(rate=2 / 3)
        adapter.controller.state.setting = replace(adapter.controller.setting, rate=1.0)
        decision = adapter.step(1000.0)
        assert decision is not None and decision.setting.rate == pytest.approx(2 / 3)
        assert "at 20 fps" in decision.log_line()
        sent = [m.frame_rate for m in game.received() if m.frame_rate is not None]
        assert sent == [pytest.approx(20.0)] and rates == [pytest.approx(20.0)]
        # A person asks 15 fps: pinned as half the target; above the configured rate is
        # refused with the reason and changes nothing.
        results: list[ControlResult] = []
        router.on_control_result = results.append
        router.handle("viewer", b'{"type":"control","seq":1,"frame_rate":15}')
        assert adapter.controller.setting.rate == pytest.approx(0.5)
        router.handle("viewer", b'{"type":"control","seq":2,"frame_rate":60}')
        router.handle("viewer", b'{"type":"control","seq":3,"target_fps":45}')
        assert [r.accepted for r in results] == [True, False, False]
        assert "above the session's configured 30 fps" in (results[1].reason or "")
        assert rates[-1] == pytest.approx(15.0)
        # A new target moves the game with it (the rate's fraction stays).
        router.handle("viewer", b'{"type":"control","seq":4,"target_fps":24}')
        assert adapter.controller.goal.target_fps == 24.0
        assert rates[-1] == pytest.approx(12.0)

    asyncio.run(scenario())


def test_auto_says_why_it_cannot_run(tmp_path: Path) -> None:
    for sub, overrides, why in (
        ("a", {"scale": None}, "not known"),
        ("b", {"upscaler": "unet"}, "unet"),
    ):
        (tmp_path / sub).mkdir()
        adapter, _, _ = _adapter(tmp_path / sub, **overrides)
        assert not adapter.enabled
        assert why in str(adapter._state["quality_reason"])


def test_a_colour_only_source_never_gets_temporal_nor_a_scale(tmp_path: Path) -> None:
    async def scenario() -> None:
        adapter, game, router = _adapter(tmp_path, source="x11", upscaler="lanczos2")
        assert adapter.controller is not None
        limits = adapter.controller.limits
        assert not (limits.scale or limits.temporal or limits.frame_generation)
        # Even if it asked, the router refuses what the source cannot do.
        results: list[ControlResult] = []
        router.on_control_result = results.append
        router.color_only = True
        router.apply_setting(AUTO_SOURCE, upscaler="temporal")
        assert results and not results[-1].accepted
        assert "needs depth, motion and jitter" in (results[-1].reason or "")
        assert game.received() == []

    asyncio.run(scenario())


@pytest.mark.slow
def test_a_served_session_under_auto_follows_its_goal_end_to_end() -> None:
    """The real path: serve's session process runs the controller, its switch reaches the
    game (a new render size) through the input router, and /sessions says what and why.
    A goal of scale 3-4 from a start at 2 makes the controller move at its first check,
    whatever the machine's load."""
    from tests.serve_harness import SMALL, serve

    args = [*SMALL, "--sessions", "1", "--broadcast-prefix", "qa", "--quality", "auto"]
    args += ["--min-scale", "3", "--max-scale", "4", "--quality-methods", "bilinear,bicubic"]
    with serve(5296, *args) as served:
        rows = served.wait(
            lambda rows: rows[0]["scale"] is not None and rows[0]["scale"] >= 3.0,
            60,
            "the session to take a scale inside its goal",
        )
        row = rows[0]
        assert row["quality"] == "auto"
        assert row["upscaler"] in ("bilinear", "bicubic")
        assert "goal" in str(row["quality_reason"])
        assert isinstance(row["expected_psnr_db"], float)
        # The game renders the new size: frames keep coming.
        frames = row["frames"]
        served.wait(lambda rows: rows[0]["frames"] > frames + 10, 30, "frames at the new scale")
        # A person asks 10 of the configured 15 fps: the game ticks slower, the session
        # publishes at that rate (a loaded machine only publishes less), and says so.
        from server.serve.control_client import request_control
        from server.session.session_control import SessionControl, StatusRecord

        broadcast = row["broadcast"]

        def ask_frame_rate(fps: float) -> StatusRecord:
            control = SessionControl(frame_rate=fps)
            url = served.player_url(broadcast)
            return asyncio.run(request_control(url, broadcast, control, timeout_s=30))

        record = ask_frame_rate(10.0)
        assert record.last_control is not None and record.last_control.accepted, record
        rows = served.wait(
            lambda rows: rows[0]["frame_rate"] == 10.0 and 0 < rows[0]["fps"] <= 12.0,
            30,
            "the session to publish at 10 fps",
        )
        frames = rows[0]["frames"]
        served.wait(lambda rows: rows[0]["frames"] > frames + 10, 30, "frames at 10 fps")
        # Above the configured rate: refused with the reason, nothing changes.
        record = ask_frame_rate(30.0)
        assert record.last_control is not None and not record.last_control.accepted
        assert "above the session's configured 15 fps" in (record.last_control.reason or "")
        assert record.frame_rate == 10.0


def test_the_host_file_reaches_the_controller_and_its_shortfall_the_status(
    tmp_path: Path,
) -> None:
    """What peers.py carries each way: another session's wait goes into the measurement;
    this session's own shortfall goes into the stream state the status track reports."""
    adapter, _, _ = _adapter(tmp_path)
    assert adapter.controller is not None
    host_file = tmp_path / "host.json"
    write_host_file(host_file, [PeerRow(1, None), PeerRow(2, 0.5, 0.25)])
    adapter.peers = HostPeers(host_file, own_index=1)
    seen: list[Measurement] = []
    real_update = adapter.controller.update

    def update(m: Measurement) -> Decision | None:
        seen.append(m)
        return real_update(m)

    adapter.controller.update = update  # type: ignore[method-assign]
    adapter.step(1000.0)
    assert (seen[-1].peer_waiting_rate, seen[-1].peer_cores_short) == (0.5, 0.25)
    assert "quality_cores_short" not in adapter._state
    adapter.controller.state.cores_short = 0.123456
    adapter.step(1001.0)
    assert adapter._state["quality_cores_short"] == 0.123
    adapter.controller.state.cores_short = None
    adapter.peers = HostPeers(None, own_index=1)  # a session on its own
    adapter.step(1002.0)
    assert seen[-1].peer_waiting_rate is None
    assert "quality_cores_short" not in adapter._state
