"""One CPU thread budget for torch, numba's parallel kernels and OpenCV."""

from __future__ import annotations

import cv2
import numba
import torch


def limit_compiled_threads(threads: int) -> None:
    """numba's parallel kernels (MPE, FSR 1 and the temporal upscaler on the CPU) get
    the same thread budget as torch.

    Unlimited they take every core, and their threads spin-wait between kernels over
    the core the game renders on: at 40 fps with frame generation on 2 cores that
    lost 22 frames in 20 s against 0 without prediction. The limit is per calling
    thread in numba, so call this on the thread that runs the kernels.
    """
    most: int = getattr(numba.config, "NUMBA_NUM_THREADS", 1)  # numba's own maximum
    numba.set_num_threads(max(1, min(threads, most)))


def set_cpu_threads(threads: int) -> None:
    """torch's intra-op threads, (on this thread) numba's and OpenCV's pool (the
    cv_* upscalers and bilinear's resize), all ``threads``: OpenCV unlimited takes
    every core of the machine, whatever the worker was given."""
    torch.set_num_threads(threads)
    limit_compiled_threads(threads)
    cv2.setNumThreads(max(1, threads))
