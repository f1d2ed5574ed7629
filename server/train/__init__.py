"""Training of the neural upscalers (``upcast train``): dataset and loop."""
