"""``upcast bench reframe``: ReFrame layer caching on the neural upscaler, and its tables."""
