# syntax=docker/dockerfile:1
# moq-dev's moq-relay and moq-token CLI from crates.io (the Rust core that the moq-rs
# Python package wraps; tests/test_moq_rs_relay.py streams upcast through it).
FROM rust:1-bookworm AS build
ARG MOQ_RELAY_VERSION=0.8.9
ARG MOQ_TOKEN_VERSION=0.5.16
RUN cargo install --locked moq-relay --version "${MOQ_RELAY_VERSION}" \
    && cargo install --locked moq-token-cli --version "${MOQ_TOKEN_VERSION}"

FROM debian:bookworm-slim
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates curl \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /usr/local/cargo/bin/moq-relay /usr/local/cargo/bin/moq-token-cli /usr/local/bin/
EXPOSE 4443/udp 4443/tcp
ENTRYPOINT ["moq-relay"]
