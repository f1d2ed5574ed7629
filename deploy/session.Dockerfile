# syntax=docker/dockerfile:1
# The session image, CPU: `upcast serve` runs N game sessions (game + upscaler worker +
# encoder each, rings in /dev/shm) and publishes them to an external relay.
FROM python:3.11-slim-bookworm
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
# CPU torch (pyproject's extra `game` pins torch==2.13.0; from PyPI that pin pulls
# CUDA wheels).
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
RUN pip install --index-url "${TORCH_INDEX_URL}" torch==2.13.0
COPY pyproject.toml README.md ./
COPY server/ server/
COPY upscalers/ upscalers/
# With the extra `game` (torch, numba, ...: the game and the upscaler worker). PyAV's
# wheel bundles FFmpeg with libx264: no system codec packages needed.
RUN pip install ".[game]"
# Compile the numba CPU kernels into their cache now (as root: site-packages is
# read-only for the upcast user), not on the first frame of a stream.
RUN python -m upscalers.warm_kernels
COPY deploy/healthcheck.py /usr/local/bin/upcast-healthcheck
RUN chmod 0755 /usr/local/bin/upcast-healthcheck && useradd --system --uid 10001 upcast
USER upcast
# Status/metrics HTTP (GET /sessions, /metrics, /healthz).
EXPOSE 4444/tcp
HEALTHCHECK --interval=5s --timeout=4s --start-period=60s --retries=10 \
    CMD ["upcast-healthcheck", "http://127.0.0.1:4444/healthz"]
CMD ["upcast", "--log-format", "json", "serve", "--relay", "http://relay:4443/", "--auth-key", "/secrets/auth.key", "--sessions", "2", "--http-port", "4444"]
