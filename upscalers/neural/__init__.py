"""Neural upscalers: a small U-Net and a U-Net++ trained on the game's own frames.

``load(name)`` gives a ready ``NeuralUpscaler`` with the shipped weights of
``weights/<name>.pt`` (see MODEL_CARD.md for how they were made).
"""

from upscalers.neural.flops import conv_flops
from upscalers.neural.upscaler import (
    NeuralUpscaler,
    UNetPlusPlusUpscaler,
    UNetUpscaler,
    load,
)

__all__ = ["NeuralUpscaler", "UNetPlusPlusUpscaler", "UNetUpscaler", "conv_flops", "load"]
