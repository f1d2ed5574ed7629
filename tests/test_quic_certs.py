"""Certificates, structured-field parsing and WebTransport error code mapping."""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from server.quic import codes, sf
from server.quic.certs import generate_cert, load_cert
from server.quic.server import choose_protocol


def test_generated_cert_follows_chromium_rules(tmp_path: Path) -> None:
    bundle = generate_cert(extra_names=["relay.example", "10.0.0.7"], directory=tmp_path)
    cert = x509.load_pem_x509_certificate(bundle.cert_pem)
    key = cert.public_key()
    assert isinstance(key, ec.EllipticCurvePublicKey)
    assert key.curve.name == "secp256r1"
    total = cert.not_valid_after_utc - cert.not_valid_before_utc
    assert total == datetime.timedelta(days=13)  # <= 14 days, backdating included
    now = datetime.datetime.now(datetime.UTC)
    assert cert.not_valid_before_utc <= now - datetime.timedelta(minutes=4)
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "relay.example"}
    assert set(san.get_values_for_type(x509.IPAddress)) == {
        ipaddress.ip_address("127.0.0.1"),
        ipaddress.ip_address("::1"),
        ipaddress.ip_address("10.0.0.7"),
    }
    der = cert.public_bytes(serialization.Encoding.DER)
    assert bundle.sha256_hex == hashlib.sha256(der).hexdigest()
    spki = cert.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    assert base64.b64decode(bundle.spki_sha256_b64) == hashlib.sha256(spki).digest()
    assert (tmp_path / "key.pem").stat().st_mode & 0o077 == 0
    loaded = load_cert(bundle.cert_path, bundle.key_path)
    assert loaded.sha256_hex == bundle.sha256_hex


def test_sf_string_lists() -> None:
    header = '"moq-lite-04", "moq-lite-03";q=1, token, "moqt-17" , "a\\"b"'
    assert sf.parse_string_list(header) == ["moq-lite-04", "moq-lite-03", "moqt-17", 'a"b']
    assert sf.parse_string_list("") == []
    assert sf.parse_string_list('"unterminated') == []
    assert sf.serialize_string("moq-lite-03") == '"moq-lite-03"'
    assert sf.parse_string(sf.serialize_string('x"\\y')) == 'x"\\y'
    with pytest.raises(ValueError):
        sf.serialize_string("é")


def test_protocol_choice_follows_client_preference() -> None:
    offered = sf.parse_string_list('"moq-lite-04", "moq-lite-03", "moqt-17"')
    assert choose_protocol(offered, ["moq-lite-03"]) == "moq-lite-03"
    assert choose_protocol(offered, ["moq-lite-03", "moq-lite-04"]) == "moq-lite-04"
    assert choose_protocol(offered, ["moql"]) is None


def test_error_code_mapping_round_trips() -> None:
    for code in (0, 1, 0x1D, 0x1E, 0x1F, 1000, 0xFFFFFFFF):
        assert codes.from_http_code(codes.to_http_code(code)) == code
    assert codes.to_http_code(0xFFFFFFFF) == codes.LAST
    assert codes.from_http_code(codes.FIRST + 0x1E) is None  # greasing codepoint
    assert codes.from_http_code(0x100) is None
