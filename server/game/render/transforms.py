"""4x4 matrices of the frame contract (see server/frames/frame.py), in float64 numpy.

Kept in float64 on the host: the renderer composes a handful of matrices per
frame, and doing it in double precision keeps the motion of a still camera
exactly zero once the result is cast to float32.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

F64Array = npt.NDArray[np.float64]


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> F64Array:
    """The contract's projection: view z in [-near, -far] -> NDC z in [0, 1]."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    return np.array(
        [
            [f / aspect, 0.0, 0.0, 0.0],
            [0.0, f, 0.0, 0.0],
            [0.0, 0.0, far / (near - far), near * far / (near - far)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


def rotation_y(yaw: float) -> F64Array:
    """3x3 rotation about +y; positive yaw turns -z (forward) towards -x (left)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_x(pitch: float) -> F64Array:
    """3x3 rotation about +x; positive pitch looks up."""
    c, s = math.cos(pitch), math.sin(pitch)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rigid(rotation: F64Array, translation: F64Array) -> F64Array:
    """4x4 matrix of x -> rotation @ x + translation."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def rigid_inverse(m: F64Array) -> F64Array:
    """Inverse of a rigid 4x4 matrix without a general inversion (exact transpose)."""
    r = m[:3, :3].T
    return rigid(r, -r @ m[:3, 3])


def halton(index: int, base: int) -> float:
    """Radical inverse of ``index`` in ``base`` (index 1 -> 1/base)."""
    result, f = 0.0, 1.0
    while index > 0:
        f /= base
        result += f * (index % base)
        index //= base
    return result


def jitter_phase_count(scale: float) -> int:
    """FSR 2's rule: 8 * scale^2 phases, truncated (18, 23, 32, 72 for 1.5, 1.7, 2, 3).

    FSR 2 casts to int (ffxFsr2GetJitterPhaseCount), so 1.7 gives 23, not ceil's 24.
    """
    # The epsilon keeps exact products (8 * 2.25) from truncating one short.
    return max(1, int(8.0 * scale * scale + 1e-6))


def jitter_offset(frame_index: int, phases: int) -> tuple[float, float]:
    """Halton(2, 3) minus 0.5 in render pixels; index 1-based like FSR 2, wrapping by frame."""
    i = frame_index % phases + 1
    return halton(i, 2) - 0.5, halton(i, 3) - 0.5
