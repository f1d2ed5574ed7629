"""The temporal upscaler (FSR 2 / DLSS class): the torch reference, its tensor helpers
and tuning, the numba CPU kernels, back-projection of the history, and the cut
detector that keeps history from blending across a scene cut."""
