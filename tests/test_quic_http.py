"""The plain HTTP side: certificate hash, static files, routes, abuse."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

from server.quic.http_fetch import fetch_cert_hash
from server.quic.http_side import HttpRequest, HttpSide, Response, serve_http

HASH = "ab" * 32


async def raw(port: int, request: bytes, host: str = "127.0.0.1") -> bytes:
    reader, writer = await asyncio.open_connection(host, port)
    writer.write(request)
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    return data


def split(response: bytes) -> tuple[int, dict[str, str], bytes]:
    head, _, body = response.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = {}
    for line in lines[1:]:
        k, _, v = line.partition(":")
        headers[k.strip().lower()] = v.strip()
    return int(lines[0].split()[1]), headers, body


def get(path: str, method: str = "GET") -> bytes:
    return f"{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode()


def with_http(tmp_path: Path, body: Callable[[int], Awaitable[None]]) -> None:
    web = tmp_path / "web"
    (web / "js").mkdir(parents=True)
    (web / "index.html").write_text("<h1>hi</h1>")
    (web / "js" / "app.js").write_text("export {}")
    (web / "app.wasm").write_bytes(b"\0asm")
    (tmp_path / "secret.txt").write_text("secret")

    async def stats(request: HttpRequest) -> Response:
        return 200, "application/json", b'{"q":"' + request.query.encode() + b'"}'

    async def main() -> None:
        side = HttpSide(HASH, web_root=web, routes={"/stats.json": stats})
        server = await serve_http(side, host="::", port=0)
        try:
            await body(server.sockets[0].getsockname()[1])
        finally:
            server.close()
            await server.wait_closed()

    asyncio.run(main())


def test_hash_static_routes(tmp_path: Path) -> None:
    async def body(port: int) -> None:
        status, headers, data = split(await raw(port, get("/certificate.sha256"), "::1"))
        assert (status, data) == (200, HASH.encode())
        assert headers["access-control-allow-origin"] == "*"
        assert "no-cache" in headers["cache-control"]
        assert await fetch_cert_hash("localhost", port) == HASH

        status, headers, data = split(await raw(port, get("/")))
        assert (status, data) == (200, b"<h1>hi</h1>")
        assert headers["content-type"].startswith("text/html")
        status, headers, _ = split(await raw(port, get("/js/app.js")))
        assert headers["content-type"].startswith("text/javascript")
        status, headers, _ = split(await raw(port, get("/app.wasm")))
        assert headers["content-type"] == "application/wasm"
        status, headers, data = split(await raw(port, get("/js/app.js", "HEAD")))
        assert (status, data, headers["content-length"]) == (200, b"", "9")
        assert split(await raw(port, get("/healthz")))[2] == b"ok"
        assert split(await raw(port, get("/stats.json?x=1")))[2] == b'{"q":"x=1"}'
        assert split(await raw(port, get("/nope")))[0] == 404
        assert split(await raw(port, get("/x", "POST")))[0] == 405

    with_http(tmp_path, body)


def test_traversal_and_abuse_refused(tmp_path: Path) -> None:
    async def body(port: int) -> None:
        for path in (
            "/../secret.txt",
            "/js/../../secret.txt",
            "/%2e%2e/secret.txt",
            "/js/..%2f..%2fsecret.txt",
            "/..\\secret.txt",
        ):
            status, _, data = split(await raw(port, get(path)))
            assert status == 404 and b"secret" not in data, path
        # Oversized head, garbage, and a slow client do not stop the server.
        big = b"GET / HTTP/1.1\r\nX: " + b"a" * 70_000 + b"\r\n\r\n"
        assert split(await raw(port, big))[0] == 431
        assert split(await raw(port, b"\x16\x03\x01garbage\r\n\r\n"))[0] == 400
        _, slow = await asyncio.open_connection("127.0.0.1", port)
        slow.write(b"GET / HT")
        # Keep-alive: two requests on one connection.
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n" * 2)
        await writer.drain()
        first = await reader.readuntil(b"ok")
        second = await reader.readuntil(b"ok")
        assert first.startswith(b"HTTP/1.1 200") and second.startswith(b"HTTP/1.1 200")
        writer.close()
        slow.close()

    with_http(tmp_path, body)


def test_shutdown_with_open_connections_logs_no_error(caplog: object) -> None:
    """A process that ends with keep-alive connections open (a browser tab still on
    the page) cancels their handlers, in the read or in the close: no traceback."""
    import logging

    import pytest

    assert isinstance(caplog, pytest.LogCaptureFixture)

    async def main() -> None:
        server = await serve_http(HttpSide("ab" * 32), host="127.0.0.1", port=0)
        port = server.sockets[0].getsockname()[1]
        writers = []
        for _ in range(3):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            await writer.drain()
            assert (await reader.readline()).startswith(b"HTTP/1.1 200")
            writers.append(writer)
        writers[0].close()  # one handler is closing its side when the cancel comes
        server.close()
        # Returning now leaves the handlers waiting: the loop's run cancels them.

    import uvloop  # the relay's loop, where the traceback showed

    with caplog.at_level(logging.ERROR):
        uvloop.run(main())
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
