"""AMD FidelityFX Super Resolution 1 (EASU, RCAS): the torch reference, the fused
function for ``torch.compile`` and the numba CPU kernels."""
