# The session image, CPU: `upcast serve` runs N game sessions (game + upscaler worker +
# encoder each, rings in /dev/shm) and publishes them to an external relay.
#
# Online by default; offline with the build arguments BASE_IMAGE and
# PYTHON_SOURCE=wheelhouse, as deploy/relay.Dockerfile explains (no `# syntax=` line
# for the same reason).
ARG BASE_IMAGE=python:3.11-slim-bookworm
FROM ${BASE_IMAGE}
ARG PYTHON_SOURCE=pypi
# CPU torch (pyproject's extra `game` pins torch==2.13.0; from PyPI that pin pulls
# CUDA wheels). Offline, the wheelhouse holds the CPU wheel (deploy/smoke.sh checks).
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/venv/bin:$PATH
# A venv, on either base: Debian's own python3 refuses system-wide pip installs.
RUN python3 -m venv /opt/venv
WORKDIR /app
# The wheelhouse is bind-mounted, not copied: no wheel stays in a layer.
RUN --mount=type=bind,source=deploy/wheelhouse,target=/wheelhouse \
    if [ "$PYTHON_SOURCE" = wheelhouse ]; then \
        export PIP_NO_INDEX=1 PIP_FIND_LINKS=/wheelhouse; \
    else \
        export PIP_INDEX_URL="$TORCH_INDEX_URL"; \
    fi && \
    pip install torch==2.13.0
COPY pyproject.toml README.md ./
COPY server/ server/
COPY upscalers/ upscalers/
# With the extra `game` (torch, numba, ...: the game and the upscaler worker). PyAV's
# wheel bundles FFmpeg with libx264: no system codec packages needed.
RUN --mount=type=bind,source=deploy/wheelhouse,target=/wheelhouse \
    if [ "$PYTHON_SOURCE" = wheelhouse ]; then \
        export PIP_NO_INDEX=1 PIP_FIND_LINKS=/wheelhouse; \
    fi && \
    pip install ".[game]"
COPY deploy/healthcheck.py /usr/local/bin/upcast-healthcheck
RUN chmod 0755 /usr/local/bin/upcast-healthcheck && useradd --system --uid 10001 upcast
# numba's cache must be writable by the user who loads it: numba refuses to cache at
# all (an import error, at the first @njit(cache=True)) where it cannot write, and
# site-packages is root's. Its own folder, given to the upcast user.
ENV NUMBA_CACHE_DIR=/var/cache/numba
# Compile the numba CPU kernels into that cache now, not on the first frame of a stream.
RUN python -m upscalers.kernels.warm && chown -R upcast /var/cache/numba
USER upcast
# Status/metrics HTTP (GET /sessions, /metrics, /healthz).
EXPOSE 4444/tcp
HEALTHCHECK --interval=5s --timeout=4s --start-period=60s --retries=10 \
    CMD ["upcast-healthcheck", "http://127.0.0.1:4444/healthz"]
# The demo stack starts both sessions whatever the host can carry (--admission admit);
# without it, serve refuses a session while another is at its adaptive-quality floor.
CMD ["upcast", "--log-format", "json", "serve", "--relay", "http://relay:4443/", "--auth-key", "/secrets/auth.key", "--sessions", "2", "--http-port", "4444", "--admission", "admit"]
