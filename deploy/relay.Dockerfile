# The relay image: `upcast relay` (moq-lite over WebTransport on UDP, HTTP on TCP, one
# port) serving the built web client, so the page, /certificate.sha256 and the
# WebTransport endpoint share one origin and one published port (no CORS, one URL).
# Also runs the `keys` init service (`upcast token generate`).
#
# Online by default (images from Docker Hub, PyPI, npm). Offline, for hosts without a
# registry (deploy/README.md, "Offline build"), with build arguments:
#   BASE_IMAGE=<local image with python3 + venv>   e.g. deploy/base-image.sh's
#   PYTHON_SOURCE=wheelhouse   pip install --no-index --find-links deploy/wheelhouse/
#   WEB_SOURCE=prebuilt        client_web/dist/ as built on the host (./dev builds it)
# No `# syntax=` line: it would pull the dockerfile frontend image from Docker Hub;
# the engine's built-in BuildKit frontend has RUN --mount and skips unused stages.
ARG BASE_IMAGE=python:3.11-slim-bookworm
ARG NODE_IMAGE=node:20-bookworm-slim
ARG WEB_SOURCE=npm

# --- the browser client (client_web/, esbuild): built here, or taken prebuilt ------
FROM ${NODE_IMAGE} AS web-npm
WORKDIR /src/client_web
COPY client_web/package.json client_web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY client_web/ ./
# build.mjs empties dist/ first: a host build in the context does not leak into this one.
RUN npm run build

FROM ${BASE_IMAGE} AS web-prebuilt
COPY client_web/dist/ /src/client_web/dist/

# Only the stage WEB_SOURCE names is built (BuildKit skips the other).
FROM web-${WEB_SOURCE} AS web

# --- Python runtime ---------------------------------------------------------------
FROM ${BASE_IMAGE}
ARG PYTHON_SOURCE=pypi
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/venv/bin:$PATH
# A venv, on either base: Debian's own python3 refuses system-wide pip installs.
RUN python3 -m venv /opt/venv
WORKDIR /app
COPY pyproject.toml README.md ./
COPY server/ server/
COPY upscalers/ upscalers/
# The base install only, without the extra `game`: the relay and `upcast token` import
# no torch, numba or scikit-image (tests/test_base_install.py runs them without).
# The wheelhouse is bind-mounted, not copied: no wheel stays in a layer.
RUN --mount=type=bind,source=deploy/wheelhouse,target=/wheelhouse \
    if [ "$PYTHON_SOURCE" = wheelhouse ]; then \
        export PIP_NO_INDEX=1 PIP_FIND_LINKS=/wheelhouse; \
    fi && \
    pip install .
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
