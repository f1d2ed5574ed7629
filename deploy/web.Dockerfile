# syntax=docker/dockerfile:1
# The web client alone, for hosting the page apart from the relay (a CDN, another
# domain). The default stack does not need it: the relay image ships the same build
# and serves it itself. Open http://HOST:8080/?relay=http://RELAY_HOST:4443/&name=game-1
# (the relay answers /certificate.sha256 with CORS, so the page may live elsewhere).
FROM node:20-bookworm-slim AS build
WORKDIR /src/client_web
COPY client_web/package.json client_web/package-lock.json ./
RUN npm ci --no-audit --no-fund --loglevel=error
COPY client_web/ ./
RUN npm run build

FROM nginx:1.27-alpine
COPY --from=build /src/client_web/dist/ /usr/share/nginx/html/
EXPOSE 80/tcp
HEALTHCHECK --interval=10s --timeout=3s --retries=5 CMD ["wget", "-q", "-O", "/dev/null", "http://127.0.0.1/index.html"]
