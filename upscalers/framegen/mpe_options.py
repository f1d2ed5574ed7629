"""Options of Mesh Projection Estimation, shared by its torch (mpe.py) and numba
(mpe_cpu.py) paths."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

DEFAULT_TILE = 16  # the paper: n between 8 and 16


@dataclass(frozen=True)
class MpeOptions:
    tile: int = DEFAULT_TILE
    tensile: bool = True
    shear: bool = True
    tensile_threshold_px: float = 1.0
    shear_tolerance: float = 0.02  # relative view-depth difference that still counts as equal
    shear_min_shift_px: float = 0.0  # the paper's "abs(InUV - prevUV) > Threshold"
    shear_iterations: int = 1
    # Larger clipped bounding boxes come from vertices next to the eye; dropped (holes).
    max_bbox_share: float = 0.125
    # "numba": compiled CPU kernels (mpe_cpu.py); "torch": mpe.py, the reference and the
    # CUDA path; "auto": numba on the CPU, torch elsewhere.
    backend: Literal["auto", "torch", "numba"] = "auto"
