"""WebTransport over aioquic: thin asyncio adapters, certificates, the HTTP side.

Generic over WtSessionHandler so the moq session plugs in without this package
knowing moq-lite.

``moq_link`` is the one module that joins a moq-lite session (``server.moq``) to a
WebTransport session. May import: ``server.moq``, ``server.ops``. Never the relay, a
session or the media layer.
"""

from .certs import CertBundle, generate_cert, load_cert
from .client import CertificateHashError, WtConnectError, connect
from .endpoints import Endpoints, serve
from .http_fetch import fetch_cert_hash
from .http_side import HttpRequest, HttpSide, serve_http
from .server import WtServer, serve_webtransport
from .session import HandlerFactory, WtRequest, WtSession, WtSessionHandler

__all__ = [
    "CertBundle",
    "CertificateHashError",
    "Endpoints",
    "HandlerFactory",
    "HttpRequest",
    "HttpSide",
    "WtConnectError",
    "WtRequest",
    "WtServer",
    "WtSession",
    "WtSessionHandler",
    "connect",
    "fetch_cert_hash",
    "generate_cert",
    "load_cert",
    "serve",
    "serve_http",
    "serve_webtransport",
]
