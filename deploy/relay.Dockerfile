# syntax=docker/dockerfile:1
# The relay image: `upcast relay` (moq-lite over WebTransport on UDP, HTTP on TCP, one
# port) serving the built web client, so the page, /certificate.sha256 and the
# WebTransport endpoint share one origin and one published port (no CORS, one URL).
# Also runs the `keys` init service (`upcast token generate`).

# --- stage 1: bundle the browser client (client_web/, esbuild) ---------------------
FROM node:20-bookworm-slim AS web
WORKDIR /src/client_web
COPY client_web/package.json client_web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY client_web/ ./
RUN npm run build

# --- stage 2: Python runtime ------------------------------------------------------
FROM python:3.11-slim-bookworm
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY server/ server/
COPY upscalers/ upscalers/
# The base install only, without the extra `game`: the relay and `upcast token` import
# no torch, numba or scikit-image (tests/test_base_install.py runs them without).
RUN pip install .
COPY --from=web /src/client_web/dist/ /app/client_web/dist/
COPY deploy/healthcheck.py /usr/local/bin/upcast-healthcheck
RUN chmod 0755 /usr/local/bin/upcast-healthcheck && useradd --system --uid 10001 upcast
USER upcast
# QUIC/WebTransport on UDP and HTTP (page, /certificate.sha256, /metrics) on TCP.
EXPOSE 4443/udp 4443/tcp
HEALTHCHECK --interval=5s --timeout=4s --start-period=10s --retries=10 \
    CMD ["upcast-healthcheck", "http://127.0.0.1:4443/certificate.sha256"]
# The self-signed certificate (14 days, ECDSA P-256, pinned by hash) is generated at start.
CMD ["upcast", "--log-format", "json", "relay", "--host", "0.0.0.0", "--port", "4443", "--web-root", "/app/client_web/dist"]
