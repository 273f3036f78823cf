"""The live view's E-stop and Links panels in headless Chromium (issue 40): STOP and Release on
the page reach the ``estop`` node (WebSocket, RTDB ``estop.web``) and its heartbeat output;
a Zenoh import's link shows online, and offline with its last contact once it falls silent.
The graph exports its own e-stop and imports it back over its Zenoh session (loopback)."""

from __future__ import annotations

from typing import Any

import pytest

from flowrt import GraphBuilder, Runtime
from tests.test_display import browser, needs_chromium
from tests.test_web_joystick import until

pytestmark = [pytest.mark.browser, pytest.mark.timeout(120)]


def graph() -> Any:
    g = GraphBuilder("web-estop")
    g.add("estop", "estop", params={"rate_hz": 20})
    g.add("view", "display", params={"port": 0})
    g.zenoh(listen=["tcp/127.0.0.1:0"])
    g.export("t/estop", "estop.output")
    g.import_("echo", {"key": "t/estop", "period": "50ms", "stale": "state"})
    return g.build()


@needs_chromium
async def test_estop_buttons_and_the_link_state_on_the_page() -> None:
    async with Runtime(graph()) as rt:
        # the page can release the e-stop: the view needs its token (in the URL to open)
        url = rt.scheduler.runners["view"].executor.node.open_url  # type: ignore[attr-defined]
        echo = rt.subscribe("echo.output", policy="latest")

        async def echoed(active: bool) -> bool:
            got = echo.drain()
            return bool(got) and got[-1].get("active") is active

        async with browser(url) as page:
            await until(lambda: page.eval("!!document.querySelector('#links')"), 20, "the page")
            await until(
                lambda: page.eval("!document.querySelector('#estoppanel').hidden"),
                20,
                "the e-stop panel",
            )
            await until(
                lambda: page.eval("(window.flowrt.estop || [])[0] === 'engaged'"),
                10,
                "engaged at start",
            )
            await until(
                lambda: page.eval("window.flowrt.links && window.flowrt.links.echo === true"),
                20,
                "the link online",
            )
            await until(lambda: page.eval("window.flowrt.connected"), 10, "the WebSocket")
            await page.eval("document.querySelector('#estoprelease').click()")
            await until(lambda: echoed(False), 10, "released, over Zenoh and back")
            await until(
                lambda: page.eval("window.flowrt.estop[0] === 'released'"), 10, "shown released"
            )
            await page.eval("document.querySelector('#estopstop').click()")
            await until(lambda: echoed(True), 10, "engaged again")
            # the exporter falls silent: the link is offline on the page, with its last contact
            rt.set_timing("estop", enabled=False)
            await until(lambda: page.eval("window.flowrt.links.echo === false"), 10, "offline")
            text = await page.eval("document.querySelector('#links').textContent")
            assert "OFFLINE, last contact" in text
            assert "never" not in text
