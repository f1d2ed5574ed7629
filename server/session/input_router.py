"""Where each viewer message goes: the game's input socket, the worker's control
socket, or the encoder.

Runs on the session's event loop. Game inputs are one Unix datagram each
(microseconds, never blocking: the socket is the game's queue). Upscaler
switches wait for the worker's reply, so they run on the default executor and
their outcome is logged; a missing worker never blocks the loop.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from server.game.input import InputMessage, send_input
from server.session.gamepad_keys import GamepadKeyMap
from server.session.session_control import ControlResult
from server.session.viewer_input import (
    BadViewerMessage,
    ControlMessage,
    GamepadMessage,
    HeldKeys,
    KeyframeMessage,
    KeysMessage,
    LookMessage,
    PointerMessage,
    ViewerMessage,
    look_input,
    parse_viewer_message,
)
from server.worker.control import SetCachePolicy, SetUpscaler, send_control
from upscalers import registry

log = logging.getLogger(__name__)

MAX_HELD = 64  # viewers whose held keys we track
MAX_GAME_KEYS = 16  # keys held at once sent to a captured application (server/game/input.py)


class InputRouter:
    def __init__(
        self,
        *,
        game_input: Path | None,
        worker_control: Path | None,
        request_keyframe: Callable[[], None],
        on_upscaler_set: Callable[[str], None] | None = None,
        on_scale_request: Callable[[float], None] | None = None,
        on_frame_generation: Callable[[bool], None] | None = None,
        on_cache_policy: Callable[[str | None], None] | None = None,
        on_encode_scale: Callable[[float], None] | None = None,
        on_frame_rate: Callable[[float], None] | None = None,
        max_frame_rate: float | None = None,
        on_control_result: Callable[[ControlResult], None] | None = None,
        on_message: Callable[[str, ViewerMessage], None] | None = None,
        color_only: bool = False,
        gamepad_keys: GamepadKeyMap | None = None,
    ) -> None:
        """``color_only``: the game is a captured application (source x11): it takes the
        viewers' raw keys, pointer and buttons, and no method that needs depth or motion,
        no scale change and no frame generation applies to it."""
        self.game_input = game_input
        self.color_only = color_only
        # The keys each viewer holds, per device ("keyboard", "gamepad0"...).
        self.raw_keys: dict[str, dict[str, frozenset[str]]] = {}
        # Gamepad buttons and sticks -> keys (a per-application map from config).
        self.gamepad_keys = gamepad_keys or GamepadKeyMap.standard()
        self.worker_control = worker_control
        self.request_keyframe = request_keyframe
        self.on_upscaler_set = on_upscaler_set
        self.on_scale_request = on_scale_request
        self.on_frame_generation = on_frame_generation
        # The encoder's size (the session's set_encode_scale); None: not adjustable here.
        self.on_encode_scale = on_encode_scale
        # The game's frame rate was set (the session's monitor and encoder follow), and
        # the highest a request may ask: the session's configured rate (None: no bound).
        self.on_frame_rate = on_frame_rate
        self.max_frame_rate = max_frame_rate
        # The worker's cache policy after a switch it accepted (None: the method has none).
        self.on_cache_policy = on_cache_policy
        # One request talks to the worker at a time, in arrival order (asyncio.Lock is
        # FIFO): a later policy must not land before an earlier switch and its policy.
        self._worker_turn = asyncio.Lock()
        # Every control request ends in exactly one result (the status track shows it).
        self.on_control_result = on_control_result
        # Sees every control result too, accepted or refused (the quality controller's
        # pins and goals, and its own requests that did not go through).
        self.on_control_outcome: Callable[[ControlResult], None] | None = None
        self._auto_seq = 0
        # Sees every accepted message with its source (the rate control reads feedback).
        self.on_message = on_message
        self.held: dict[str, HeldKeys] = {}
        self.accepted = 0
        self.refused = 0
        self._last_tick = time.monotonic()

    def handle(self, source: str, payload: bytes) -> None:
        """One frame from viewer broadcast ``source``; bad ones are counted and logged."""
        try:
            message = parse_viewer_message(payload)
        except BadViewerMessage as exc:
            self.refused += 1
            log.warning("input from %s refused: %s", source, exc)
            self._refuse_bad_control(source, payload, str(exc))
            return
        self.accepted += 1
        if self.on_message is not None:
            self.on_message(source, message)
        if isinstance(message, LookMessage):
            if not self.color_only:
                self._to_game(look_input(message))
            elif message.locked:  # otherwise the same drag comes as `pointer` messages
                self._to_game(
                    InputMessage(pointer_dx=message.dx, pointer_dy=message.dy, seq=message.seq)
                )
        elif isinstance(message, PointerMessage):
            if self.color_only:
                self._to_game(
                    InputMessage(
                        pointer_x=message.x,
                        pointer_y=message.y,
                        buttons=message.buttons,
                        seq=message.seq,
                    )
                )
        elif isinstance(message, KeysMessage):
            self._keys(source, "keyboard", frozenset(k.lower() for k in message.down), message.seq)
        elif isinstance(message, GamepadMessage):
            pad = f"gamepad{message.index}"
            self._keys(source, pad, self.gamepad_keys.keys_for(message), message.seq)
        elif isinstance(message, ControlMessage):
            self._control(source, message)
        elif isinstance(message, KeyframeMessage):
            self.request_keyframe()

    def forget(self, source: str) -> None:
        """The viewer left: its held keys are released."""
        self.held.pop(source, None)
        if any(self.raw_keys.pop(source, {}).values()) and self.color_only:
            self._to_game(InputMessage(keys_down=self._all_raw_keys()))

    def _keys(self, source: str, device: str, keys: frozenset[str], seq: int) -> None:
        """The keys one device of a viewer holds changed (keyboard, or a gamepad mapped
        to keys): a captured application gets the union of every viewer's and device's
        keys; the built-in game moves the camera by the viewer's union."""
        devices = self.raw_keys.get(source)
        if devices is None:
            if len(self.raw_keys) >= MAX_HELD:
                return
            devices = self.raw_keys[source] = {}
        devices[device] = keys
        if self.color_only:
            self._to_game(InputMessage(keys_down=self._all_raw_keys(), seq=seq))
            return
        held = self.held.get(source)
        if held is None:
            held = self.held[source] = HeldKeys()
        viewer_keys = sorted(set().union(*devices.values()))[:MAX_GAME_KEYS]
        held.update(KeysMessage(type="keys", down=viewer_keys, seq=seq))
        # Move at once, so the press shows in the very next frame (input-to-photon).
        step = held.step(1 / 60)
        if step is not None:
            self._to_game(step)

    def _all_raw_keys(self) -> list[str]:
        union: set[str] = set()
        for devices in self.raw_keys.values():
            for keys in devices.values():
                union |= keys
        return sorted(union)[:MAX_GAME_KEYS]

    def tick(self) -> None:
        """Called once per game frame: held keys keep moving the camera."""
        now = time.monotonic()
        dt = now - self._last_tick
        self._last_tick = now
        for held in self.held.values():
            step = held.step(dt)
            if step is not None:
                self._to_game(step)

    def _to_game(self, message: InputMessage) -> None:
        if self.game_input is None:
            return
        try:
            send_input(self.game_input, message)
        except OSError as exc:  # the game is restarting: inputs meanwhile are lost
            log.debug("game input socket: %s", exc)

    def _report(self, result: ControlResult) -> None:
        level = logging.INFO if result.accepted else logging.WARNING
        log.log(level, "control %d from %s: %s%s", result.seq, result.source,
                "accepted" if result.accepted else "refused",
                f" ({result.reason})" if result.reason else "")  # fmt: skip
        if self.on_control_result is not None:
            self.on_control_result(result)
        if self.on_control_outcome is not None:
            self.on_control_outcome(result)

    def apply_setting(
        self,
        source: str,
        *,
        upscaler: str | None = None,
        scale: float | None = None,
        frame_generation: bool | None = None,
        encode_scale: float | None = None,
        frame_rate: float | None = None,
    ) -> int | None:
        """A setting the session chose itself (the quality controller): the same path,
        checks and log lines as a person's control request from ``source``. Returns the
        request's seq (its result carries it), None when it asks nothing."""
        asked = (upscaler, scale, frame_generation, encode_scale, frame_rate)
        if all(x is None for x in asked):
            return None
        self._auto_seq += 1
        message = ControlMessage(
            type="control",
            seq=self._auto_seq,
            upscaler=upscaler,
            scale=scale,
            frame_generation=frame_generation,
            encode_scale=encode_scale,
            frame_rate=frame_rate,
        )
        self._control(source, message)
        return self._auto_seq

    def _refuse_bad_control(self, source: str, payload: bytes, reason: str) -> None:
        """A control request that failed validation still gets an answer, with its seq."""
        try:
            raw = json.loads(payload)
        except ValueError:
            return
        if not isinstance(raw, dict) or raw.get("type") != "control":
            return
        seq = raw.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool) or not 0 <= seq < 1 << 53:
            seq = 0
        self._report(ControlResult(seq=seq, source=source, accepted=False, reason=reason))

    def _control(self, source: str, message: ControlMessage) -> None:
        requested = message.requested()
        problems = []
        if not requested:
            problems.append(
                "empty control request: set upscaler, scale, cache_policy, frame_generation, "
                "encode_scale, frame_rate and/or the quality goal (quality, target_fps, "
                "preference, min_scale, max_scale, methods)"
            )
        if message.upscaler is not None and message.upscaler not in registry.available():
            problems.append(
                f"upscaler: unknown {message.upscaler!r}; available: "
                + ", ".join(registry.available())
            )
        elif (
            message.cache_policy is not None
            and message.upscaler is not None
            and not registry.takes_option(message.upscaler, "policy")
        ):
            # Refused before the switch, so the request is not half-applied.
            problems.append(f"cache_policy: upscaler {message.upscaler!r} has no layer cache")
        problems += _goal_problems(message)
        problems += _frame_rate_problems(message, self.max_frame_rate)
        if self.color_only:
            problems += _color_only_problems(message)
        for name in ("upscaler", "cache_policy"):
            if name in requested and self.worker_control is None:
                problems.append(f"{name}: this session has no worker control socket")
        if message.encode_scale is not None and self.on_encode_scale is None:
            problems.append("encode_scale: this session's encoder size is fixed")
        if problems:
            # Nothing of a refused request is applied: a half-applied one is harder to read.
            self._report(
                ControlResult(
                    seq=message.seq,
                    source=source,
                    accepted=False,
                    reason="; ".join(problems),
                    requested=requested,
                )
            )
            return
        if message.scale is not None:
            # The game renders at display / scale from its next frame; the worker
            # upscales whatever size arrives, and the RESET flag restarts history.
            self._to_game(InputMessage(render_scale=message.scale, seq=message.seq))
            log.info("render scale %.3g requested by %s", message.scale, source)
            if self.on_scale_request is not None:
                self.on_scale_request(message.scale)
        if message.frame_generation is not None:
            # The game alternates full renders with dynamic-only ticks; the worker
            # predicts whatever arrives flagged PREDICTED, so it needs no message.
            self._to_game(InputMessage(frame_generation=message.frame_generation, seq=message.seq))
            log.info(
                "frame generation %s requested by %s",
                "on" if message.frame_generation else "off",
                source,
            )
            if self.on_frame_generation is not None:
                self.on_frame_generation(message.frame_generation)
        if message.frame_rate is not None:
            # The game ticks at the new rate from its next frame (game time keeps its
            # pace); the session judges its rate and budgets its bits against it.
            self._to_game(InputMessage(frame_rate=message.frame_rate, seq=message.seq))
            log.info("frame rate %.3g fps requested by %s", message.frame_rate, source)
            if self.on_frame_rate is not None:
                self.on_frame_rate(message.frame_rate)
        if message.encode_scale is not None:
            assert self.on_encode_scale is not None  # refused above otherwise
            log.info("encode scale %.3g requested by %s", message.encode_scale, source)
            self.on_encode_scale(message.encode_scale)
        result = ControlResult(seq=message.seq, source=source, accepted=True, requested=requested)
        if message.upscaler is not None or message.cache_policy is not None:
            # The worker answers; the result waits for its reply.
            asyncio.get_running_loop().create_task(
                self._to_worker(message.upscaler, message.cache_policy, result)
            )
        else:
            self._report(result)

    async def _to_worker(
        self, upscaler: str | None, cache_policy: str | None, result: ControlResult
    ) -> None:
        """Switch the method, then its cache policy; the first refusal ends the request."""
        async with self._worker_turn:
            refused = await self._switch_then_set_policy(upscaler, cache_policy)
        if refused is not None:
            result = result.model_copy(update={"accepted": False, "reason": refused})
        self._report(result)

    async def _switch_then_set_policy(
        self, upscaler: str | None, cache_policy: str | None
    ) -> str | None:
        refused: str | None = None
        if upscaler is not None:
            refused = await self._ask_worker("upscaler", SetUpscaler(name=upscaler))
            if refused is None:
                log.info("upscaler switched to %s", upscaler)
                # Jitter only helps a method that accumulates it; otherwise it is shimmer.
                if not self.color_only:
                    self._to_game(InputMessage(jitter=registry.is_temporal(upscaler)))
                if self.on_upscaler_set is not None:
                    self.on_upscaler_set(upscaler)
        if cache_policy is not None and (upscaler is None or refused is None):
            refused = await self._ask_worker("cache_policy", SetCachePolicy(policy=cache_policy))
            if refused is None:
                log.info("cache policy set to %s", cache_policy)
        return refused

    async def _ask_worker(self, field: str, message: SetUpscaler | SetCachePolicy) -> str | None:
        """Send one control message; None if the worker accepted it, else why not."""
        assert self.worker_control is not None
        loop = asyncio.get_running_loop()
        try:
            reply = await loop.run_in_executor(None, send_control, self.worker_control, message)
        except (OSError, TimeoutError) as exc:
            log.warning("worker control %s failed: %s", message.op, exc)
            return f"{field}: the worker did not answer ({exc})"
        if not reply.get("ok"):
            log.warning("worker refused %s: %s", message.op, reply.get("error"))
            return f"{field}: the worker refused: {reply.get('error')}"
        if self.on_cache_policy is not None:
            policy = reply.get("cache_policy")
            self.on_cache_policy(policy if isinstance(policy, str) else None)
        return None


def _goal_problems(message: ControlMessage) -> list[str]:
    """What is wrong with a request's quality goal (the quality controller's bounds)."""
    problems = []
    unknown = [m for m in message.methods or [] if m not in registry.available()]
    if unknown:
        problems.append(
            f"methods: unknown {', '.join(map(repr, unknown))}; available: "
            + ", ".join(registry.available())
        )
    low, high = message.min_scale, message.max_scale
    if low is not None and high is not None and low > high:
        problems.append(f"min_scale {low:g} is above max_scale {high:g}")
    return problems


def _frame_rate_problems(message: ControlMessage, highest: float | None) -> list[str]:
    """A frame rate or a goal above what the session was configured for: its encoder,
    budgets and the viewers' buffers were sized for that rate at most."""
    if highest is None:
        return []
    problems = []
    for name in ("frame_rate", "target_fps"):
        value = getattr(message, name)
        if value is not None and value > highest + 1e-6:
            problems.append(f"{name} {value:g} is above the session's configured {highest:g} fps")
    return problems


def _color_only_problems(message: ControlMessage) -> list[str]:
    """What a colour-only source (a captured application) cannot do."""
    problems = []
    if message.upscaler is not None and registry.is_temporal(message.upscaler):
        spatial = [m for m in registry.available() if not registry.is_temporal(m)]
        problems.append(
            f"upscaler: {message.upscaler!r} needs depth, motion and jitter, which this "
            f"source (a captured application) does not give; available: {', '.join(spatial)}"
        )
    if message.scale is not None:
        problems.append(
            "scale: this source is captured at the size the application draws at; "
            "it cannot change at run time"
        )
    if message.frame_generation:
        problems.append("frame_generation: needs depth and motion, which this source does not give")
    return problems
