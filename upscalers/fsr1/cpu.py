"""The numba backend of FSR 1 on the CPU: host buffers around ``fsr1_cpu_kernels``.

Same math and options as the torch classes (``fsr1_easu.Easu``, ``fsr1_rcas.Rcas``),
which stay the reference and the CUDA path; see ``fsr1_cpu_kernels`` for why
loops beat eager torch here. Scratch buffers are kept per geometry; each call
returns a fresh (3, H, W) uint8 tensor (a view of an (H, W, 3) array, the ring U
layout, so writing it into a slot is one copy).
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import numpy.typing as npt
import torch

from upscalers.fsr1 import cpu_kernels as kernels
from upscalers.fsr1.easu import PAD, axis_map

log = logging.getLogger(__name__)

_compiled_logged = False


def usable_input(color: object) -> npt.NDArray[np.uint8] | None:
    """The frame's colour as an (H, W, 3) uint8 numpy array, or None when it is not one
    (a tensor on a GPU, a float image): the torch path handles those."""
    if not isinstance(color, np.ndarray):
        return None
    if color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] != 3:
        return None
    return color


class Fsr1Cpu:
    """EASU, and optionally RCAS, of (H, W, 3) uint8 frames; one instance per thread."""

    def __init__(self) -> None:
        self._key: tuple[int, int, int, int] | None = None

    def _setup(self, h: int, w: int, ho: int, wo: int) -> None:
        if self._key == (h, w, ho, wo):
            return
        self._key = (h, w, ho, wo)
        self._row_f, self._phase_y = _axis(h, ho)
        self._col_f, self._phase_x = _axis(w, wo)
        # An integer horizontal scale k repeats k phases along a row (the fast kernel):
        # columns 0 .. k - 1 stand for all.
        k = wo // w if wo % w == 0 else 0
        self._integer = k > 0
        self._col0 = self._col_f[:k].copy()
        self._phase_x0 = self._phase_x[:k].copy()
        self._padded = np.empty((3, h + 2 * PAD, w + 2 * PAD), np.float32)
        self._luma = np.empty((h + 2 * PAD, w + 2 * PAD), np.float32)
        self._fields = np.empty((3, h + 2, w + 2), np.float32)
        # EASU's output with a 1-pixel border: RCAS's edge-repeated neighbours.
        self._easu = np.empty((3, ho + 2, wo + 2), np.float32)

    def __call__(
        self, color: npt.NDArray[np.uint8], out_hw: tuple[int, int], rcas_scale: float | None
    ) -> torch.Tensor:
        """EASU of ``color`` to ``out_hw`` (rows, columns), then RCAS with its lobe scaled
        by ``rcas_scale`` (None: no RCAS), as a (3, H_out, W_out) uint8 tensor."""
        h, w, _ = color.shape
        ho, wo = out_hw
        self._setup(h, w, ho, wo)
        t0 = time.monotonic()
        kernels.pad_and_fields(color, self._padded, self._luma, self._fields)
        if self._integer:
            kernels.easu_integer(
                self._padded,
                self._fields,
                self._row_f,
                self._phase_y,
                self._col0,
                self._phase_x0,
                self._easu,
            )
        else:
            kernels.easu_gathered(
                self._padded,
                self._fields,
                self._row_f,
                self._col_f,
                self._phase_y,
                self._phase_x,
                self._easu,
            )
        out = np.empty((ho, wo, 3), np.uint8)
        rows = out.reshape(ho, wo * 3)  # a view: see kernels._row_to_rgb8
        if rcas_scale is None:
            kernels.interior_to_rgb8(self._easu, rows)
        else:
            kernels.rcas_to_rgb8(self._easu, np.float32(rcas_scale), rows)
        _log_first_call(time.monotonic() - t0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return torch.from_numpy(out).permute(2, 0, 1)


def _axis(n_in: int, n_out: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float32]]:
    """Padded index of texel 'f' and the phase of every output pixel along one axis; at
    an integer scale k exactly f = (o - k // 2) // k and the k phases repeat, as the
    torch path's ``_NearestSampler`` has them."""
    if n_out % n_in == 0:
        k = n_out // n_in
        o = np.arange(n_out, dtype=np.int64)
        _, phase = axis_map(1, k)
        f = (o - k // 2) // k
        return f + PAD, np.tile(phase.numpy().astype(np.float32), n_in)
    base, phase = axis_map(n_in, n_out)
    return (base + PAD).numpy().astype(np.int64), phase.numpy().astype(np.float32)


def _log_first_call(took: float) -> None:
    """The first call compiles the kernels (or loads them from numba's disk cache)."""
    global _compiled_logged
    if not _compiled_logged:
        _compiled_logged = True
        log.info("FSR 1 CPU kernels ready in %.1f s (compiled or loaded from cache)", took)
