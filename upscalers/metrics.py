"""Image quality figures: PSNR, SSIM, FLIP, and frame-to-frame error change.

All take (H, W, 3) uint8 sRGB images (what reaches a player) and compare
against a reference of the same size.
"""

from __future__ import annotations

import itertools

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

U8Image = npt.NDArray[np.uint8]


def _check_pair(reference: U8Image, test: U8Image) -> None:
    if reference.shape != test.shape or reference.ndim != 3 or reference.shape[2] != 3:
        raise ValueError(f"images must both be (H, W, 3), got {reference.shape} and {test.shape}")
    if reference.dtype != np.uint8 or test.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {reference.dtype} and {test.dtype}")


def psnr(reference: U8Image, test: U8Image) -> float:
    """Peak signal-to-noise ratio in dB over all channels; inf for identical images."""
    _check_pair(reference, test)
    diff = reference.astype(np.float64) - test.astype(np.float64)
    mse = float(np.mean(diff * diff))
    return float("inf") if mse == 0.0 else 10.0 * float(np.log10(255.0**2 / mse))


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def ssim(reference: U8Image, test: U8Image) -> float:
    """Mean SSIM (Wang et al. 2004: 11x11 Gaussian, sigma 1.5, K1 0.01, K2 0.03),
    per channel then averaged, valid region only (no padding artefacts)."""
    _check_pair(reference, test)
    x = torch.from_numpy(reference).permute(2, 0, 1).unsqueeze(1).to(torch.float32) / 255.0
    y = torch.from_numpy(test).permute(2, 0, 1).unsqueeze(1).to(torch.float32) / 255.0
    g = _gaussian_window()
    kx = g.view(1, 1, 1, -1)
    ky = g.view(1, 1, -1, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, kx), ky)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return float((num / den).mean())


def flip(reference: U8Image, test: U8Image) -> float:
    """Mean LDR FLIP error (NVIDIA's flip-evaluator, default 67 pixels per degree).

    flip-evaluator ends the process on arguments it dislikes, so everything is
    checked here first.
    """
    _check_pair(reference, test)
    if min(reference.shape[:2]) < 8:
        raise ValueError(f"FLIP needs images of at least 8x8, got {reference.shape[:2]}")
    import flip_evaluator

    ref = np.ascontiguousarray(reference, dtype=np.float32) / 255.0
    tst = np.ascontiguousarray(test, dtype=np.float32) / 255.0
    _, mean_error, _ = flip_evaluator.evaluate(ref, tst, "LDR", applyMagma=False)
    return float(mean_error)


def signed_error(reference: U8Image, test: U8Image) -> npt.NDArray[np.float32]:
    """Per-pixel signed error in [−1, 1], the input of the flicker figure."""
    _check_pair(reference, test)
    return (test.astype(np.float32) - reference.astype(np.float32)) / 255.0


def flicker(errors: list[npt.NDArray[np.float32]]) -> float:
    """Temporal instability: mean over consecutive frames of mean |e_t − e_(t−1)|.

    A method that is wrong the same way every frame scores 0; one whose error
    jumps from frame to frame (shimmer, crawling edges) scores high.
    """
    if len(errors) < 2:
        return float("nan")
    steps = [float(np.mean(np.abs(b - a))) for a, b in itertools.pairwise(errors)]
    return float(np.mean(steps))
