"""Minimal HTTP/1.1 GET for /certificate.sha256 (no HTTP client dependency)."""

from __future__ import annotations

import asyncio
import re

_HEX64 = re.compile(r"[0-9a-f]{64}")


async def http_get(host: str, port: int, path: str, *, timeout: float = 5.0) -> tuple[int, bytes]:
    """GET http://host:port/path; returns (status, body). Reads until the server closes."""
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_connection(host, port)
        try:
            authority = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
            writer.write(
                f"GET {path} HTTP/1.1\r\nHost: {authority}\r\nConnection: close\r\n\r\n".encode()
            )
            await writer.drain()
            raw = await reader.read(1 << 20)
            while chunk := await reader.read(1 << 20):
                raw += chunk
        finally:
            writer.close()
    head, _, body = raw.partition(b"\r\n\r\n")
    status_line = head.split(b"\r\n", 1)[0].split()
    if len(status_line) < 2 or not status_line[1].isdigit():
        raise ConnectionError(f"bad HTTP response from {host}:{port}{path}")
    return int(status_line[1]), body


async def fetch_cert_hash(host: str, port: int, *, timeout: float = 5.0) -> str:
    """The server's certificate SHA-256 (hex) from http://host:port/certificate.sha256."""
    try:
        status, body = await http_get(host, port, "/certificate.sha256", timeout=timeout)
    except TimeoutError:
        raise ConnectionError(
            f"no answer for http://{host}:{port}/certificate.sha256 within {timeout:g}s"
        ) from None
    text = body.decode("ascii", "replace").strip().lower()
    if status != 200 or not _HEX64.fullmatch(text):
        raise ConnectionError(
            f"http://{host}:{port}/certificate.sha256 gave status {status} and no SHA-256 hex"
        )
    return text
