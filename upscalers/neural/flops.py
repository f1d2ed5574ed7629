"""FLOPs of a network's convolutions, per named submodule.

Counted from the shapes seen in one forward pass (forward hooks on every
``nn.Conv2d``): 2 x output elements x (input channels / groups) x kernel area,
plus the output elements for the bias. A multiply-add is 2 FLOPs, as torch's
FlopCounterMode counts. Activations, concatenations and bilinear upsampling are
left out (memory-bound, under 2 % of the total on these networks).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


def _conv_flops(conv: nn.Conv2d, out: torch.Tensor) -> int:
    kh, kw = conv.kernel_size
    per_output = 2 * (conv.in_channels // conv.groups) * kh * kw
    if conv.bias is not None:
        per_output += 1
    return int(out.numel()) * per_output


def conv_flops(model: nn.Module, input_shape: tuple[int, ...]) -> dict[str, int]:
    """FLOPs of one forward on a zero input of ``input_shape``, keyed by the dotted name
    of every submodule ("" is the whole model) and summed over the convolutions inside."""
    per_conv: dict[str, int] = {}
    handles = []
    names = {m: n for n, m in model.named_modules()}

    def hook(module: nn.Module, _inputs: Any, output: torch.Tensor) -> None:
        assert isinstance(module, nn.Conv2d)
        name = names[module]
        per_conv[name] = per_conv.get(name, 0) + _conv_flops(module, output)

    for module in names:
        if isinstance(module, nn.Conv2d):
            handles.append(module.register_forward_hook(hook))
    try:
        p = next(model.parameters())
        with torch.no_grad():
            model(torch.zeros(input_shape, device=p.device, dtype=p.dtype))
    finally:
        for h in handles:
            h.remove()
    totals = {name: 0 for name in names.values()}
    for conv_name, flops in per_conv.items():
        for name in totals:
            if name == "" or conv_name == name or conv_name.startswith(name + "."):
                totals[name] += flops
    return totals
