"""AMD FidelityFX Super Resolution 1 (spatial): EASU, and EASU followed by RCAS.

The math lives in ``fsr1_easu`` and ``fsr1_rcas``; this module adapts it to the
upscaler interface. Both run on the device given at construction (CPU by default;
a CUDA device moves the colour plane there) in float32, or in float16 on CUDA
when asked.

Backends: on the CPU in float32 the numba kernels of ``fsr1_cpu`` run by default
(``backend="auto"``; about 9x faster than eager torch at 2x); ``backend="torch"``
keeps the banded eager torch code (the reference, and the CUDA path), and
``compile=True`` runs ``fsr1_fused`` through torch.compile instead (same result
within float rounding; see ``compiled.py``).
"""

from __future__ import annotations

from typing import ClassVar

import torch

from server.frames.frame import RenderFrame, Size
from upscalers.base import BACKENDS, Backend, Upscaler, numba_can_run
from upscalers.fsr1.cpu import Fsr1Cpu, usable_input
from upscalers.fsr1.easu import PAD, Easu, axis_map, replicate_pad_into
from upscalers.fsr1.fused import easu_fused, easu_rcas_fused
from upscalers.fsr1.rcas import DEFAULT_SHARPNESS, Rcas
from upscalers.kernels.compiled import CompiledFunction
from upscalers.kernels.readiness import kernels_ready
from upscalers.spatial.resample import color_as_nchw


def frame_color(frame: RenderFrame, device: torch.device) -> torch.Tensor:
    """The (3, H, W) uint8 colour plane of a frame on ``device`` (a view on the CPU)."""
    color = color_as_nchw(frame.color)[0]
    return color if device.type == "cpu" else color.to(device, non_blocking=False)


class _Fsr1Base(Upscaler):
    def __init__(
        self,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        compile: bool = False,
        backend: Backend = "auto",
    ) -> None:
        self.device = torch.device(device)
        if dtype not in (torch.float32, torch.float16, torch.bfloat16):
            raise ValueError(f"dtype must be a float dtype, got {dtype}")
        self.dtype = dtype
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        numba_ok = numba_can_run(self.device, dtype) and not compile
        if backend == "numba" and not numba_ok:
            raise ValueError(
                "backend='numba' runs on the CPU in float32 without compile=True, got "
                f"device={self.device}, dtype={dtype}, compile={compile}"
            )
        # The numba kernels take (H, W, 3) uint8 frames on the CPU; anything else (a
        # tensor already on a GPU) goes through torch whatever the backend.
        # "auto" waits for the kernels to be compiled (kernel_readiness) rather than
        # compiling them on the stream's first frame.
        use_numba = numba_ok and (
            backend == "numba" or (backend == "auto" and kernels_ready("FSR 1"))
        )
        self._cpu: Fsr1Cpu | None = Fsr1Cpu() if use_numba else None
        self.backend: Backend = "numba" if self._cpu is not None else "torch"
        self._easu = Easu(dtype=dtype)
        # compile=True: one fused inductor kernel instead of the banded eager ops.
        self.compiled: CompiledFunction | None = None
        self._geometry: tuple[object, ...] | None = None
        self._fused_args: tuple[torch.Tensor, ...] = ()
        self._fused_padded: torch.Tensor | None = None

    def _fused_inputs(
        self, color: torch.Tensor, out_hw: tuple[int, int]
    ) -> tuple[torch.Tensor, ...]:
        """The padded input and the per-geometry tap indices and phases of fsr1_fused."""
        _, h, w = color.shape
        ho, wo = out_hw
        key = (h, w, ho, wo, color.device)
        if key != self._geometry:
            self._geometry = key
            bx, fx = axis_map(w, wo)
            by, fy = axis_map(h, ho)
            dev, dt = color.device, self.dtype
            self._fused_args = (
                (by + PAD).view(-1, 1).to(dev),
                (bx + PAD).view(1, -1).to(dev),
                fy.to(dt).view(-1, 1).to(dev),
                fx.to(dt).view(1, -1).to(dev),
            )
            self._fused_padded = torch.empty((3, h + 2 * PAD, w + 2 * PAD), dtype=dt, device=dev)
        assert self._fused_padded is not None
        replicate_pad_into(color, self._fused_padded, PAD)
        return (self._fused_padded, *self._fused_args)


class EasuUpscaler(_Fsr1Base):
    """FSR 1 EASU alone: edge-adaptive Lanczos-like upscale, de-ringed, no sharpening."""

    name: ClassVar[str] = "easu"

    def __init__(
        self,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        compile: bool = False,
        backend: Backend = "auto",
    ) -> None:
        super().__init__(device, dtype, compile, backend)
        if compile:
            self.compiled = CompiledFunction(easu_fused, "easu")

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        out_hw = (display_size.height, display_size.width)
        rgb = usable_input(frame.color) if self._cpu is not None else None
        if self._cpu is not None and rgb is not None:
            return self._cpu(rgb, out_hw, rcas_scale=None)
        color = frame_color(frame, self.device)
        if self.compiled is not None:
            return self.compiled(*self._fused_inputs(color, out_hw))  # type: ignore[no-any-return]
        return self._easu(color, out_hw)


class EasuRcasUpscaler(_Fsr1Base):
    """FSR 1 as shipped: EASU, then RCAS sharpening.

    ``sharpness`` is in stops below the strongest (FSR's convention: 0 is the
    strongest, each stop halves the effect); ``denoise`` enables RCAS's optional
    noise removal (torch only: ``backend="auto"`` then runs torch).
    """

    name: ClassVar[str] = "easu_rcas"

    def __init__(
        self,
        sharpness: float = DEFAULT_SHARPNESS,
        denoise: bool = False,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        compile: bool = False,
        backend: Backend = "auto",
    ) -> None:
        if denoise and backend == "numba":
            raise ValueError("backend='numba' does not implement RCAS denoise")
        super().__init__(device, dtype, compile, "torch" if denoise else backend)
        self._rcas = Rcas(sharpness=sharpness, denoise=denoise)
        self._padded: torch.Tensor | None = None
        if compile:
            if denoise:
                raise ValueError("compile=True does not implement RCAS denoise")
            self.compiled = CompiledFunction(easu_rcas_fused, "easu_rcas")

    @property
    def sharpness(self) -> float:
        return self._rcas.sharpness

    def upscale(self, frame: RenderFrame, display_size: Size) -> torch.Tensor:
        h, w = display_size.height, display_size.width
        rgb = usable_input(frame.color) if self._cpu is not None else None
        if self._cpu is not None and rgb is not None:
            return self._cpu(rgb, (h, w), rcas_scale=self._rcas.scale)
        color = frame_color(frame, self.device)
        if self.compiled is not None:
            args = self._fused_inputs(color, (h, w))
            return self.compiled(*args, self._rcas.scale)  # type: ignore[no-any-return]
        shape = (3, h + 2, w + 2)
        if (
            self._padded is None
            or self._padded.shape != shape
            or self._padded.device != color.device
        ):
            self._padded = torch.empty(shape, dtype=self.dtype, device=color.device)
        # EASU writes straight into the interior of RCAS's padded input.
        self._easu(color, (h, w), out=self._padded[:, 1:-1, 1:-1])
        return self._rcas(self._padded)
