# syntax=docker/dockerfile:1
# The session image on an NVIDIA GPU: same program as session.Dockerfile, CUDA torch.
# Run it with deploy/docker-compose.cuda.yml (needs the NVIDIA Container Toolkit).
FROM nvidia/cuda:12.6.3-runtime-ubuntu22.04
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    DEBIAN_FRONTEND=noninteractive
# upcast needs Python 3.11 (jammy-updates has it); a venv keeps pip off the system Python.
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3.11 python3.11-venv ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /app
# The CUDA 12.6 build of the pinned torch (it brings its own cuDNN/cuBLAS wheels).
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cu126
RUN pip install --index-url "${TORCH_INDEX_URL}" torch==2.13.0
COPY pyproject.toml README.md ./
COPY server/ server/
COPY upscalers/ upscalers/
# With the extra `game` (the game and the upscaler worker); torch is the one above.
RUN pip install ".[game]"
COPY deploy/healthcheck.py /usr/local/bin/upcast-healthcheck
RUN chmod 0755 /usr/local/bin/upcast-healthcheck && useradd --system --uid 10001 upcast
# numba must be able to write its cache (session.Dockerfile found it refuses to import
# the CPU kernels otherwise); here they compile on first use, into this folder.
ENV NUMBA_CACHE_DIR=/var/cache/numba
RUN mkdir -p /var/cache/numba && chown upcast /var/cache/numba
USER upcast
EXPOSE 4444/tcp
HEALTHCHECK --interval=5s --timeout=4s --start-period=60s --retries=10 \
    CMD ["upcast-healthcheck", "http://127.0.0.1:4444/healthz"]
# The demo stack starts both sessions whatever the host can carry (--admission admit);
# without it, serve refuses a session while another is at its adaptive-quality floor.
CMD ["upcast", "--log-format", "json", "serve", "--relay", "http://relay:4443/", "--auth-key", "/secrets/auth.key", "--sessions", "2", "--http-port", "4444", "--admission", "admit"]
