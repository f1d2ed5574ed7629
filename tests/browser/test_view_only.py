"""The page's token: ``?jwt=`` goes onto the relay URL; without one the page only watches
(no input broadcast, controls off, and it says so). No relay runs here."""

from __future__ import annotations

from typing import Any

from tests.browser.conftest import DIST
from tests.browser.test_bundle import _closed_port_url, _page
from tests.chromium import browser_marks

pytestmark = browser_marks(DIST / "index.html")


def _settled(page: Any) -> dict[str, Any]:
    page.wait_for_function("() => window.upcast && window.upcast.stats().status !== 'starting'")
    return page.evaluate(  # type: ignore[no-any-return]
        "() => ({viewOnly: window.upcast.viewOnly, url: window.upcast.config.url.toString(),"
        " hint: document.querySelector('.hint').textContent,"
        " disabled: Object.fromEntries([...document.querySelectorAll("
        "'#controls select, #controls button')].map(e => [e.id, e.disabled]))})"
    )


def test_without_token_the_page_is_view_only(web_root: str, browser: Any) -> None:
    relay = _closed_port_url()
    with _page(browser, f"{web_root}/index.html?url={relay}&broadcast=game") as (page, errors):
        state = _settled(page)
    assert errors == []
    assert state["viewOnly"] is True
    assert "view only" in state["hint"] and "inputs are off" in state["hint"]
    assert state["disabled"] and all(state["disabled"].values())
    assert "jwt" not in state["url"]


def test_token_rides_on_the_relay_url(web_root: str, browser: Any) -> None:
    relay = _closed_port_url()
    url = f"{web_root}/index.html?url={relay}&broadcast=game&jwt=abc.def.ghi"
    with _page(browser, url) as (page, errors):
        state = _settled(page)
    assert errors == []
    assert state["viewOnly"] is False
    assert state["url"] == f"{relay}?jwt=abc.def.ghi"
    # Every control is on, except the cache policy while the upscaler has no layer cache.
    assert state["disabled"].pop("cache-policy") is True
    assert state["disabled"] and not any(state["disabled"].values())
