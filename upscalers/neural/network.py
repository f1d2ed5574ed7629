"""Network names -> classes, the checkpoint format, and the step from features to image.

A checkpoint is a ``torch.save``d dict that ``torch.load(weights_only=True)``
reads: ``format``, ``model`` (a name of ``MODELS``), ``widths``,
``in_channels``, ``scale``, ``base`` (the upsampling under the residual; absent:
bilinear), ``state_dict`` (float16 tensors: half the bytes, and
the weights lose nothing measurable at 8-bit output) and ``meta`` (how it was
trained: free-form strings and numbers for the model card).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from upscalers.names import DEFAULT_NETWORK_BASE, check_network_base
from upscalers.neural.features import base_phases, feature_channels, jitter_of
from upscalers.neural.unet import UNet
from upscalers.neural.unetpp import UNetPlusPlus

MODELS: dict[str, type[UNet] | type[UNetPlusPlus]] = {"unet": UNet, "unetpp": UNetPlusPlus}
CHECKPOINT_FORMAT = 1
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def build_model(
    name: str,
    scale: int = 2,
    widths: tuple[int, ...] | None = None,
    base: str = DEFAULT_NETWORK_BASE,
) -> nn.Module:
    """An untrained network whose output is the upsampling ``base`` (names.NETWORK_BASES)."""
    check_network_base(base)
    try:
        cls = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r}; allowed: {', '.join(MODELS)}") from None
    out = 3 * scale * scale
    model = (
        cls(feature_channels(scale), out)
        if widths is None
        else cls(feature_channels(scale), out, widths)
    )
    # The residual starts at zero, so an untrained network is exactly the bilinear
    # upsampling and training starts from there. The output convolution is the last
    # one registered in both networks.
    last = [m for m in model.modules() if isinstance(m, nn.Conv2d)][-1]
    assert last.out_channels == out
    nn.init.zeros_(last.weight)
    if last.bias is not None:
        nn.init.zeros_(last.bias)
    set_base(model, base)
    return model


def base_of(model: nn.Module) -> str:
    """The upsampling the network's residual is added to."""
    return str(getattr(model, "upsampling_base", DEFAULT_NETWORK_BASE))


def set_base(model: nn.Module, base: str) -> None:
    """Change the upsampling under the residual (fine-tuning a network onto another
    base); the weights stay, so the output changes until it is trained again."""
    check_network_base(base)
    # A plain attribute (torch's stubs type Module attributes as tensors or modules).
    object.__setattr__(model, "upsampling_base", base)


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
            "base": base_of(model),
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
    # Checkpoints from before the base was recorded were all trained on bilinear.
    base = str(ckpt.get("base", DEFAULT_NETWORK_BASE))
    try:
        check_network_base(base)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    model = build_model(name, scale, tuple(int(w) for w in ckpt["widths"]) or None, base)
    model.load_state_dict({k: v.float() for k, v in ckpt["state_dict"].items()})
    model.eval()
    return name, model, scale, dict(ckpt.get("meta", {}))


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return x
    return F.pad(x, (0, pw, 0, ph), mode="replicate")


def local_range(color: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3, h, w) colour -> the min and max of each render pixel's 3x3 neighbourhood
    (edges replicated), each (N, 3, h, w)."""
    padded = F.pad(color, (1, 1, 1, 1), mode="replicate")
    return -F.max_pool2d(-padded, 3, stride=1), F.max_pool2d(padded, 3, stride=1)


def predict(model: nn.Module, features: torch.Tensor, scale: int) -> torch.Tensor:
    """Features (N, C, h, w) -> image (N, 3, s h, s w): the network's residual on top of
    its base upsampling (bilinear or Catmull-Rom, ``base_of``) of the colour from where
    its samples really lay (jitter compensated), clamped to the 3x3 range of the
    frame's own colour around each display pixel's render pixel, as the temporal
    upscaler's output is: detail without a halo or ringing past the input's local
    range (the unclamped game-only U-Net took a 64|191 step to 57..197). Training goes
    through the same clamp.
    Any h, w (padded to the network's multiple, cropped back)."""
    h, w = features.shape[-2:]
    multiple = int(getattr(model, "multiple", 1))
    x = pad_to_multiple(features, multiple)
    residual = model(x)[..., :h, :w]
    color = features[:, :3]
    phases = base_phases(color, scale, jitter_of(features), base_of(model)) + residual
    # Viewed as (N, 3, s s, h, w), every sub-pixel phase of a render pixel takes that
    # pixel's range by broadcasting (pixel_shuffle order: channel c s s + phase).
    lo, hi = local_range(color)
    grouped = phases.reshape(color.shape[0], 3, scale * scale, h, w)
    clamped = torch.clamp(grouped, lo.unsqueeze(2), hi.unsqueeze(2))
    return F.pixel_shuffle(clamped.reshape(phases.shape), scale)


def with_memory_format(model: nn.Module, fmt: torch.memory_format) -> nn.Module:
    """``model.to(memory_format=...)`` (channels-last convolutions are about twice as fast
    on the CPU, measured); typed here once since torch's stubs lack the keyword."""
    return model.to(memory_format=fmt)  # type: ignore[call-overload,no-any-return]
