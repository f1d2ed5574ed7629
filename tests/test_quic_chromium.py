"""Real headless Chromium against the WebTransport server (the wire truth)."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS
from server.quic import Endpoints, generate_cert, serve
from tests.test_quic_wt import SERVER_HANDLERS, echo_factory

PAGE = """<!doctype html><meta charset="utf-8"><title>wt</title>
<script type="module">
const hex = await (await fetch("/certificate.sha256")).text();
const hash = new Uint8Array(hex.match(/../g).map((b) => parseInt(b, 16)));
const out = {};
try {
  const wt = new WebTransport(`https://localhost:${location.port}/game`, {
    serverCertificateHashes: [{ algorithm: "sha-256", value: hash }],
    protocols: ["moq-lite-04", "moq-lite-03"],
  });
  await wt.ready;
  out.protocol = wt.protocol;
  const stream = await wt.createBidirectionalStream();
  const writer = stream.writable.getWriter();
  await writer.write(new TextEncoder().encode("hello from chromium"));
  await writer.close();
  let text = "";
  const reader = stream.readable.getReader();
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    text += new TextDecoder().decode(value);
  }
  out.echo = text;
  // A server-opened unidirectional stream reaches the page too.
  const cmd = await wt.createUnidirectionalStream();
  const w2 = cmd.getWriter();
  await w2.write(new TextEncoder().encode("cmd:open-uni:pushed"));
  await w2.close();
  const uni = wt.incomingUnidirectionalStreams.getReader();
  const { value: incoming } = await uni.read();
  out.pushed = await new Response(incoming).text();
  wt.close({ closeCode: 0, reason: "bye" });
} catch (e) {
  out.error = String(e);
}
window.result = out;
</script>"""


@pytest.mark.slow
@pytest.mark.skipif(
    not os.environ.get("CI") and not CHROMIUM.exists(),
    reason="needs /usr/bin/chromium (apt install chromium); never skipped in CI",
)
def test_chromium_webtransport_echo(tmp_path: Path) -> None:
    from playwright import async_api as playwright_api

    (tmp_path / "web").mkdir()
    (tmp_path / "web" / "index.html").write_text(PAGE)
    cert = generate_cert(directory=tmp_path / "cert")

    async def main() -> dict[str, str]:
        SERVER_HANDLERS.clear()
        endpoints: Endpoints = await serve(
            echo_factory, cert, host="::", port=0, web_root=tmp_path / "web"
        )
        try:
            async with playwright_api.async_playwright() as p:
                browser = await p.chromium.launch(
                    executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS)
                )
                try:
                    page = await browser.new_page()
                    await page.goto(f"http://localhost:{endpoints.port}/")
                    handle = await page.wait_for_function("window.result", timeout=20_000)
                    result: dict[str, str] = await handle.json_value()
                finally:
                    await browser.close()
            # The page's close reaches the server handler exactly once.
            async with asyncio.timeout(5):
                while not (SERVER_HANDLERS and SERVER_HANDLERS[0].closed):
                    await asyncio.sleep(0.05)
            assert len(SERVER_HANDLERS[0].closed) == 1
            return result
        finally:
            await endpoints.close()

    result = asyncio.run(main())
    assert result == {
        "protocol": "moq-lite-03",
        "echo": "hello from chromium",
        "pushed": "pushed",
    }
