"""Network names -> classes, the checkpoint format, and the step from features to image.

A checkpoint is a ``torch.save``d dict that ``torch.load(weights_only=True)``
reads: ``format``, ``model`` (a name of ``MODELS``), ``widths``,
``in_channels``, ``scale``, ``head`` (``HEADS``; absent in the first checkpoints,
which are ``residual``), ``state_dict`` (float16 tensors: half the bytes, and
the weights lose nothing measurable at 8-bit output) and ``meta`` (how it was
trained: free-form strings and numbers for the model card).

Two output heads turn the network's planes into an image:

- ``residual``: 3 s s planes added to a bilinear upsampling of the colour. The
  warped history is only an input, so accumulating over many frames has to be
  learnt as "copy the history", which 10-frame training sequences teach poorly
  (the first U-Net peaked at frame 3 on a still scene and sank after).
- ``blend``: 3 s s residual planes plus s s blend-weight logits, one per display
  sub-pixel phase: image = a * warped history + (1 - a) * (bilinear + residual),
  a = sigmoid(logit) * history valid. That is a learnt temporal accumulator
  (the hand-written ``temporal`` upscaler's blend, with the weight and the
  correction predicted per pixel): an exponential history keeps accumulating
  past the training sequence's length, and a is 0 wherever the history does not
  reproject onto the screen, by construction rather than by training.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from upscalers.neural.features import (
    HISTORY_VALID_CHANNEL,
    WARPED_HISTORY_START,
    bilinear_phases,
    feature_channels,
    jitter_of,
)
from upscalers.neural.unet import UNet
from upscalers.neural.unetpp import UNetPlusPlus

MODELS: dict[str, type[UNet] | type[UNetPlusPlus]] = {"unet": UNet, "unetpp": UNetPlusPlus}
CHECKPOINT_FORMAT = 1
HEADS = ("residual", "blend")
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def head_of(model: nn.Module) -> str:
    return str(getattr(model, "head", "residual"))


def build_model(
    name: str, scale: int = 2, widths: tuple[int, ...] | None = None, head: str = "blend"
) -> nn.Module:
    try:
        cls = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r}; allowed: {', '.join(MODELS)}") from None
    if head not in HEADS:
        raise ValueError(f"unknown output head {head!r}; allowed: {', '.join(HEADS)}")
    out = 3 * scale * scale + (scale * scale if head == "blend" else 0)
    model = (
        cls(feature_channels(scale), out)
        if widths is None
        else cls(feature_channels(scale), out, widths)
    )
    # The residual and the blend logits start at zero, so an untrained network is the
    # bilinear upsampling (residual head) or its even mix with the warped history
    # (blend head), and training starts from there. The output convolution is the
    # last one registered in both networks.
    last = [m for m in model.modules() if isinstance(m, nn.Conv2d)][-1]
    assert last.out_channels == out
    nn.init.zeros_(last.weight)
    if last.bias is not None:
        nn.init.zeros_(last.bias)
    # A plain attribute (nn.Module's stubs only admit tensors and modules as attributes).
    model.head = head  # type: ignore[assignment]
    return model


def save_checkpoint(
    path: Path, name: str, model: nn.Module, scale: int, meta: dict[str, Any]
) -> None:
    state = {k: v.detach().to("cpu", torch.float16) for k, v in model.state_dict().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "model": name,
            "widths": list(getattr(model, "widths", ())),
            "in_channels": feature_channels(scale),
            "scale": scale,
            "head": head_of(model),
            "state_dict": state,
            "meta": meta,
        },
        path,
    )


def load_checkpoint(path: Path) -> tuple[str, nn.Module, int, dict[str, Any]]:
    """(name, model in float32 eval mode on the CPU, scale, meta); ValueError names what
    is wrong with a file that is not one of ours."""
    if not path.is_file():
        raise FileNotFoundError(f"no network weights at {path} (train them: upcast train)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated or foreign file: say which
        raise ValueError(f"{path}: not a readable checkpoint ({e})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not an upcast network checkpoint (format {CHECKPOINT_FORMAT})")
    name, scale = str(ckpt["model"]), int(ckpt["scale"])
    head = str(ckpt.get("head", "residual"))
    model = build_model(name, scale, tuple(int(w) for w in ckpt["widths"]) or None, head)
    model.load_state_dict({k: v.float() for k, v in ckpt["state_dict"].items()})
    model.eval()
    return name, model, scale, dict(ckpt.get("meta", {}))


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return x
    return F.pad(x, (0, pw, 0, ph), mode="replicate")


def predict(model: nn.Module, features: torch.Tensor, scale: int) -> torch.Tensor:
    """Features (N, C, h, w) -> image (N, 3, s h, s w): the network's residual on top of
    a bilinear upsampling of the colour from where its samples really lay (jitter
    compensated), blended with the warped history under the ``blend`` head (see the
    module docstring), clamped to [0, 1]. Any h, w (padded to the network's
    multiple, cropped back)."""
    h, w = features.shape[-2:]
    multiple = int(getattr(model, "multiple", 1))
    x = pad_to_multiple(features, multiple)
    out = model(x)[..., :h, :w]
    n = scale * scale
    phases = bilinear_phases(features[:, :3], scale, jitter_of(features)) + out[:, : 3 * n]
    if head_of(model) == "blend":
        valid = features[:, HISTORY_VALID_CHANNEL : HISTORY_VALID_CHANNEL + 1]
        alpha = torch.sigmoid(out[:, 3 * n :]).mul(valid).repeat(1, 3, 1, 1)  # c n + phase
        warped = features[:, WARPED_HISTORY_START : WARPED_HISTORY_START + 3 * n]
        phases = torch.lerp(phases, warped, alpha)
    return F.pixel_shuffle(phases, scale).clamp(0.0, 1.0)


def with_memory_format(model: nn.Module, fmt: torch.memory_format) -> nn.Module:
    """``model.to(memory_format=...)`` (channels-last convolutions are about twice as fast
    on the CPU, measured); typed here once since torch's stubs lack the keyword."""
    return model.to(memory_format=fmt)  # type: ignore[call-overload,no-any-return]
