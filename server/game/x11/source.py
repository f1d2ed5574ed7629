"""An X11 application as the game: the display captured into ring R, input injected.

``X11Source`` is what the game loop (server/game/loop.py) calls a renderer: each tick
it captures the display straight into the slot's colour plane and stamps the frame
COLOR_ONLY (a captured picture has no depth, motion or jitter; the worker runs only
spatial methods on it). The loop stamps the last applied input seq as for the
built-in game, so input-to-photon is measured the same way.

It owns what it started: the virtual display (unless it was given an existing one)
and the application. When the application exits, ``on_app_exit`` decides: "stop"
ends the session with the application's exit code, "restart" starts it again (at
most ``MAX_RESTARTS`` times in a row within ``RESTART_WINDOW_S``, so a program that
dies at start does not spin).
"""

from __future__ import annotations

import logging
import os
import shlex
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Generic, Literal, TypeVar

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from server.game.input import InputMessage
from server.game.loop import SourceEnded
from server.game.render.renderer import RenderTargets
from server.game.x11.app import Application
from server.game.x11.capture import ScreenCapture
from server.game.x11.display import VirtualDisplay
from server.game.x11.errors import DisplayGone
from server.game.x11.inject import InputInjector
from server.game.x11.pulse import PulseServer

log = logging.getLogger(__name__)

AppExitPolicy = Literal["stop", "restart"]
T = TypeVar("T")
MAX_RESTARTS = 3
DISPLAY_GONE_CODE = 70  # the game process's exit code when its display died (stack/local.py)
RESTART_WINDOW_S = 30.0
# A key or button tapped for less than this stays down this long: programs read their
# input state once per frame of their own, and a loaded game at 15-20 fps misses a
# press shorter than its frame (SuperTux on 2 cores did; a person's tap is ~100 ms).
MIN_TAP_S = 0.08


class ApplicationEnded(SourceEnded):
    """The application exited and the policy is to stop; ``code`` is its exit code."""

    def __init__(self, code: int) -> None:
        super().__init__(f"the application exited with code {code}", code)


class HeldUntilSeen(Generic[T]):
    """What is held down: what the viewers want, plus what was pressed less than
    ``min_hold_s`` ago and already released again (a tap)."""

    def __init__(self, min_hold_s: float = MIN_TAP_S) -> None:
        self.min_hold_s = min_hold_s
        self.wanted: frozenset[T] = frozenset()
        self.down: frozenset[T] = frozenset()
        self._pressed_at: dict[T, float] = {}

    def want(self, wanted: frozenset[T], now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        for item in wanted - self.down:
            self._pressed_at[item] = now
        self.wanted = wanted
        self._forget_old(now)
        self.down = wanted | frozenset(self._pressed_at)

    def next_tick(self, now: float | None = None) -> bool:
        """Release the taps held long enough; True if that changed what is down."""
        self._forget_old(time.monotonic() if now is None else now)
        down = self.wanted | frozenset(self._pressed_at)
        changed = down != self.down
        self.down = down
        return changed

    def _forget_old(self, now: float) -> None:
        for item, at in list(self._pressed_at.items()):
            if now - at >= self.min_hold_s:
                del self._pressed_at[item]


def _bits(mask: int) -> frozenset[int]:
    return frozenset(1 << i for i in range(mask.bit_length()) if mask >> i & 1)


class X11Source:
    """A captured X11 display with its application, as a FrameRenderer."""

    def __init__(
        self,
        size: Size,
        command: Sequence[str] | None,
        *,
        display: str | None = None,
        on_app_exit: AppExitPolicy = "stop",
        app_env: dict[str, str] | None = None,
        pulse_dir: Path | None = None,
    ) -> None:
        """``display``: an existing X server (":0") to capture instead of a new Xvfb;
        ``command``: the application to start on it (None: capture what is there)."""
        self.render_size = size
        self.on_app_exit = on_app_exit
        self._virtual: VirtualDisplay | None = None
        if display is None:
            self._virtual = VirtualDisplay.start(size.width, size.height)
            display = self._virtual.name
        self.display = display
        self._command = list(command) if command else None
        self._app_env = app_env or {}
        # The program's sound goes to a PulseAudio server of this session (pulse.py).
        self.pulse = PulseServer.start(pulse_dir) if pulse_dir is not None else None
        self.app: Application | None = None
        self.exit_code: int | None = None
        self._restarts: list[float] = []
        self._first = True
        self._keys: HeldUntilSeen[str] = HeldUntilSeen()
        self._buttons: HeldUntilSeen[int] = HeldUntilSeen()
        self._pointer_at: tuple[float, float] | None = None
        self._buttons_waiting: list[int] = []  # see apply_input
        try:
            self._capture = ScreenCapture(display, size.width, size.height)
            self._injector = InputInjector(display, size.width, size.height)
            if self._command:
                self._start_app()
        except BaseException:
            self.close()
            raise

    @property
    def environment(self) -> dict[str, str]:
        """The application's environment: DISPLAY, and SDL sound off unless asked for."""
        sound = self.pulse.app_env() if self.pulse is not None else {"SDL_AUDIODRIVER": "dummy"}
        env = {**sound, **self._app_env}
        if self._virtual is not None:
            return self._virtual.env(env)
        return {**os.environ, **env, "DISPLAY": self.display}

    def _start_app(self) -> None:
        assert self._command is not None
        self.app = Application.start(self._command, self.environment)
        log.info(
            "application started on display %s (pid %d): %s",
            self.display,
            self.app.pid,
            shlex.join(self._command),
        )

    def _check_app(self) -> None:
        """Apply the exit policy once the application has exited."""
        if self.app is None:
            return
        code = self.app.exit_code()
        if code is None:
            return
        now = time.monotonic()
        self._restarts = [t for t in self._restarts if now - t < RESTART_WINDOW_S]
        if self.on_app_exit == "restart" and len(self._restarts) < MAX_RESTARTS:
            self._restarts.append(now)
            log.warning(
                "the application exited with code %d; restarting it (%d of %d within %.0f s)",
                code,
                len(self._restarts),
                MAX_RESTARTS,
                RESTART_WINDOW_S,
            )
            self._injector.release_all()
            self._start_app()
            self._first = True  # a new program: the picture starts over
            return
        if self.on_app_exit == "restart":
            log.error(
                "the application exited with code %d after %d restarts within %.0f s; "
                "the session stops",
                code,
                MAX_RESTARTS,
                RESTART_WINDOW_S,
            )
        else:
            log.warning("the application exited with code %d; the session stops", code)
        self.exit_code = code
        self.app = None
        raise ApplicationEnded(code)

    # -- the FrameRenderer protocol ------------------------------------------------------

    def scene_cut_between(self, t0: float, t1: float) -> bool:
        return False  # never asked: frame generation is off for colour-only frames

    def render(
        self, frame_index: int, t: float, targets: RenderTargets | None = None
    ) -> RenderFrame:
        self._check_app()
        self._release_taps()
        if targets is None:
            targets = RenderTargets.allocate(self.render_size)
        try:
            self._capture.grab_into(targets.color)
        except DisplayGone as exc:
            self.exit_code = DISPLAY_GONE_CODE
            raise SourceEnded(
                f"the X display {self.display} is gone: {exc}", DISPLAY_GONE_CODE
            ) from exc
        flags = FrameFlags.COLOR_ONLY
        if self._first:
            flags |= FrameFlags.RESET
            self._first = False
        return RenderFrame(
            color=targets.color,
            depth=targets.depth,
            motion=targets.motion,
            dynamic_mask=targets.dynamic_mask,
            meta=FrameMeta(frame_id=frame_index, camera=Camera.identity(), flags=flags),
        )

    def render_dynamic(
        self, frame_index: int, t: float, targets: RenderTargets | None = None
    ) -> RenderFrame:
        return self.render(frame_index, t, targets)

    def apply_input(self, event: InputMessage) -> None:
        """Keys, pointer and buttons of one viewer message, in that order.

        A key or button released less than MIN_TAP_S after its press (a quick tap;
        both messages may be drained at the start of one tick) stays down until a
        tick after MIN_TAP_S: programs that poll their input state once per frame of
        their own would never see a press that lasted microseconds."""
        if event.keys_down is not None:
            self._keys.want(frozenset(event.keys_down))
            self._injector.set_keys_down(self._keys.down)
        jumped = False
        if event.pointer_x is not None and event.pointer_y is not None:
            position = (event.pointer_x, event.pointer_y)
            jumped = position != self._pointer_at
            self._pointer_at = position
            self._injector.move_pointer_to(*position)
        if event.pointer_dx or event.pointer_dy:
            self._injector.move_pointer_by(event.pointer_dx, event.pointer_dy)
        if event.buttons is not None:
            if jumped or self._buttons_waiting:
                # A press that comes with a jump of the pointer (a touch, a click with
                # no move before it) lands a tick after the move, as on a real mouse:
                # menus (Neverball's) act on what the pointer was over when pressed.
                self._buttons_waiting.append(event.buttons)
            else:
                self._set_buttons(event.buttons)

    def _set_buttons(self, mask: int) -> None:
        self._buttons.want(_bits(mask))
        self._injector.set_buttons(sum(self._buttons.down))

    def _release_taps(self) -> None:
        """A new tick: a press waiting for its move goes out, taps held long enough are
        released."""
        waiting, self._buttons_waiting = self._buttons_waiting, []
        for mask in waiting:  # a press and its release, in order (the tap hold applies)
            self._set_buttons(mask)
        if self._keys.next_tick():
            self._injector.set_keys_down(self._keys.down)
        if self._buttons.next_tick():
            self._injector.set_buttons(sum(self._buttons.down))

    def set_render_size(self, render_size: Size, scale: float) -> None:
        # The captured screen has the size the application draws at; a scale change
        # would need the program to redraw at another size. The session refuses it
        # before it gets here; a stray request changes nothing.
        log.warning("render scale change ignored: an X11 source captures at %s", self.render_size)

    def set_jitter(self, on: bool) -> None:
        pass  # a captured picture cannot be jittered

    # -- lifetime ------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the application, then the display; safe to call twice."""
        if self.app is not None:
            code = self.app.stop()
            log.info("application stopped (code %s)", code)
            self.app = None
        for part in ("_injector", "_capture"):
            obj = getattr(self, part, None)
            if obj is not None:
                try:
                    obj.close()
                except Exception as exc:  # the display may be gone already
                    log.debug("%s close: %s", part, exc)
        if self._virtual is not None:
            self._virtual.close()
            self._virtual = None
        if getattr(self, "pulse", None) is not None:
            assert self.pulse is not None
            self.pulse.close()
            self.pulse = None
