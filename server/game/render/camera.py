"""Camera poses, and the player's input layered on top of a scripted camera path."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from server.game.render.transforms import F64Array, rigid, rigid_inverse, rotation_x, rotation_y

MAX_PITCH_DEG = 85.0


@dataclass(frozen=True)
class CameraPose:
    """Where the camera is and where it looks: yaw about +y, then pitch about local x."""

    position: tuple[float, float, float]
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    def rotation(self) -> F64Array:
        """Camera -> world rotation (3x3)."""
        return rotation_y(math.radians(self.yaw_deg)) @ rotation_x(math.radians(self.pitch_deg))

    def view_matrix(self) -> F64Array:
        """World -> view (4x4), the contract's ``view``."""
        return rigid_inverse(rigid(self.rotation(), np.asarray(self.position, dtype=np.float64)))


@dataclass(frozen=True)
class CameraInput:
    """One input event from a player: look deltas in degrees, moves in metres.

    Moves are in the player's look frame (forward = where the player looks,
    ignoring pitch so that walking stays level), like a first-person game.
    """

    dyaw_deg: float = 0.0
    dpitch_deg: float = 0.0
    forward: float = 0.0
    right: float = 0.0
    up: float = 0.0


@dataclass(frozen=True)
class InputState:
    """Accumulated player offset relative to the scripted camera ("rig") frame."""

    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    # Offset in the rig frame (x right, y up, -z forward of the scripted camera's yaw).
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class GameCamera:
    """Applies player input on top of a scripted pose; deterministic per event sequence.

    The offset lives in the scripted camera's yaw frame, so a player who walked
    forward keeps riding along with an orbiting script instead of being left behind.
    """

    state: InputState = field(default_factory=InputState)

    def apply_input(self, event: CameraInput) -> None:
        s = self.state
        yaw = s.yaw_deg + event.dyaw_deg
        pitch = min(MAX_PITCH_DEG, max(-MAX_PITCH_DEG, s.pitch_deg + event.dpitch_deg))
        # Move along the player's new look yaw, expressed in the rig frame.
        step = rotation_y(math.radians(yaw)) @ np.array([event.right, event.up, -event.forward])
        ox, oy, oz = (float(a + b) for a, b in zip(s.offset, step, strict=True))
        self.state = InputState(yaw, pitch, (ox, oy, oz))

    def reset(self) -> None:
        self.state = InputState()

    def pose(self, scripted: CameraPose, state: InputState | None = None) -> CameraPose:
        """The scripted pose with ``state`` (default: the current one) applied."""
        s = self.state if state is None else state
        rig = rotation_y(math.radians(scripted.yaw_deg))
        world_offset = rig @ np.asarray(s.offset, dtype=np.float64)
        pos = np.asarray(scripted.position, dtype=np.float64) + world_offset
        pitch = min(MAX_PITCH_DEG, max(-MAX_PITCH_DEG, scripted.pitch_deg + s.pitch_deg))
        return CameraPose(
            (float(pos[0]), float(pos[1]), float(pos[2])), scripted.yaw_deg + s.yaw_deg, pitch
        )
