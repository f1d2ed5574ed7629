"""Who may publish and subscribe on the relay: JWT tokens compatible with moq-dev's
moq-token/moq-relay (HS256, claims ``root``/``put``/``get``/``exp``/``iat``), the JWK
key file they are signed with, and the grant a verified token becomes.

May import: ``server.moq`` (paths), ``server.quic`` (refusals). Never the relay or a session.
"""

from .authorizer import Authorizer
from .grant import Grant
from .keys import AuthKey, KeyFileError, generate_key, load_key
from .tokens import Claims, TokenError, sign, verify

__all__ = [
    "AuthKey",
    "Authorizer",
    "Claims",
    "Grant",
    "KeyFileError",
    "TokenError",
    "generate_key",
    "load_key",
    "sign",
    "verify",
]
