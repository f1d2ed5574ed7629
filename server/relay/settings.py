"""What ``upcast relay`` is told on its command line, validated at start.

Errors name the field (``invalid relay configuration: max_backlog_kib: ...``); the
docs/configuration.md's reference is generated from this model.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from server.moq.limits import IngressLimits
from server.quic.congestion_register import DEFAULT_ALGORITHM, algorithm_names, check_algorithm
from server.quic.guard import GuardLimits

_DEFAULT_INGRESS = IngressLimits()
_DEFAULT_GUARD = GuardLimits()


class RelaySettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    host: str = Field(default="::", description="address to bind (`::` = all, dual stack)")
    port: int = Field(default=4443, ge=0, le=65535, description="UDP (QUIC) and TCP (HTTP) port")
    web_root: Path | None = Field(
        default=None, description="built web client to serve (default: client_web/dist if built)"
    )
    cert: Path | None = Field(default=None, description="certificate PEM (default: generated)")
    key: Path | None = Field(default=None, description="private key PEM of `cert`")
    max_backlog_kib: int = Field(
        default=2048, ge=16, description="queued for one viewer before it skips ahead (KiB)"
    )
    max_latency_ms: int = Field(
        default=500,
        ge=0,
        description="lag after which a viewer skips to the newest group (0: backlog only)",
    )
    max_sessions: int = Field(default=1000, ge=1, description="sessions open at once")
    auth_key: Path | None = Field(
        default=None, description="JWK key file tokens are verified with (`upcast token generate`)"
    )
    public_viewers: bool = Field(
        default=True, description="sessions without a token may watch (never publish)"
    )
    no_auth: bool = Field(
        default=False, description="open relay for local development: anyone may publish"
    )
    viewer_upload_kib_s: int = Field(
        default=_DEFAULT_INGRESS.viewer_bytes_per_s // 1024,
        ge=1,
        description="upload rate of a session without publish rights before it is closed (KiB/s)",
    )
    publisher_upload_mib_s: int = Field(
        default=_DEFAULT_INGRESS.publisher_bytes_per_s // (1024 * 1024),
        ge=1,
        description="upload rate of a publishing session before it is closed (MiB/s)",
    )

    max_connections_per_source: int = Field(
        default=_DEFAULT_GUARD.max_connections_per_source,
        ge=1,
        description="QUIC connections open at once from one IP address",
    )
    new_connections_per_s: float = Field(
        default=_DEFAULT_GUARD.new_connections_per_s_per_source,
        gt=0,
        description="new QUIC connections per second from one IP address (burst: twice that)",
    )
    connect_deadline_s: float = Field(
        default=_DEFAULT_GUARD.connect_deadline_s,
        gt=0,
        description="seconds a QUIC connection has to get its WebTransport CONNECT accepted",
    )
    congestion_control: str = Field(
        default=DEFAULT_ALGORITHM,
        description="QUIC congestion controller: "
        + ", ".join(algorithm_names())
        + f" ({DEFAULT_ALGORITHM} holds the rate under random loss; reno/cubic halve it)",
    )

    @field_validator("congestion_control")
    @classmethod
    def _registered(cls, value: str) -> str:
        return check_algorithm(value)

    @model_validator(mode="after")
    def _consistent(self) -> RelaySettings:
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together")
        if self.auth_key is None and not self.no_auth:
            raise ValueError(
                "no auth_key: anyone could publish. Make a key with `upcast token generate"
                " --key PATH` and pass --auth-key PATH, or pass --no-auth for an open relay"
                " (local development only)"
            )
        if self.auth_key is not None and self.no_auth:
            raise ValueError("auth_key and no_auth exclude each other")
        if self.web_root is not None and not (self.web_root / "index.html").is_file():
            raise ValueError(
                f"web_root {self.web_root} has no index.html"
                " (build it: cd client_web && npm ci && npm run build)"
            )
        return self

    def guard(self) -> GuardLimits:
        return GuardLimits(
            max_connections_per_source=self.max_connections_per_source,
            new_connections_per_s_per_source=self.new_connections_per_s,
            new_connections_burst_per_source=2 * self.new_connections_per_s,
            connect_deadline_s=self.connect_deadline_s,
        )

    def ingress(self) -> IngressLimits:
        return IngressLimits(
            viewer_bytes_per_s=self.viewer_upload_kib_s * 1024,
            viewer_burst_bytes=4 * self.viewer_upload_kib_s * 1024,
            publisher_bytes_per_s=self.publisher_upload_mib_s * 1024 * 1024,
            publisher_burst_bytes=self.publisher_upload_mib_s * 1024 * 1024,
        )
