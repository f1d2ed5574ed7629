"""Compiled kernels in one place: numba warm-up (``python -m upscalers.kernels.warm``),
whether the kernels are ready, and the opt-in ``torch.compile`` of a hot function."""
