"""Who can drive (issue 37 item 6): when the graph can drive from the live view's page (a
joystick with ``source: web``), the view needs a token by default, generated at start and
printed as the URL to open; ``token_required: false`` is the explicit opt-out."""

from __future__ import annotations

import re
from types import SimpleNamespace

import aiohttp
import pytest
from flowrt.nodes.station.display import _drivers

from flowrt import GraphBuilder, Runtime

pytestmark = [pytest.mark.subprocess, pytest.mark.timeout(120)]


def test_only_a_graph_that_can_drive_from_the_page_needs_the_token() -> None:
    g = GraphBuilder("watch")
    g.add("joy", "joystick", params={"source": "evdev:gamepad"})
    g.add("view", "display", params={"port": 0})
    assert _drivers(SimpleNamespace(graph=g.build())) == []
    g.add("pad", "joystick", params={"source": "web"})
    assert _drivers(SimpleNamespace(graph=g.build())) == ["pad"]


async def test_the_page_that_drives_needs_the_printed_token(
    capsys: pytest.CaptureFixture[str],
) -> None:
    g = GraphBuilder("drive")
    g.add("joy", "joystick", params={"source": "web"})
    g.add("view", "display", params={"port": 0})
    g.add("open", "display", params={"port": 0, "token_required": False})
    jar = aiohttp.CookieJar(unsafe=True)  # cookies of an IP address, as a browser keeps them
    async with Runtime(g.build()) as rt, aiohttp.ClientSession(cookie_jar=jar) as http:
        view = rt.runner("view").executor.node  # type: ignore[attr-defined]
        opened = rt.runner("open").executor.node  # type: ignore[attr-defined]
        printed = capsys.readouterr().out
        m = re.search(
            r"display: (\S+) needs its token: joy can drive from the page; open (\S+)", printed
        )
        assert m, printed
        assert (m.group(1), m.group(2)) == (view.url, view.open_url)
        assert re.fullmatch(re.escape(view.url) + r"/\?token=[\w-]{16,}", view.open_url)
        for path in ("/", "/stats.json", "/ws", "/api/record"):
            async with http.get(view.url + path) as r:
                assert r.status == 401, path
        async with http.get(view.open_url) as r:
            assert r.status == 200
            assert "SESSION" in await r.text()
        async with http.get(view.url + "/stats.json") as r:  # the cookie keeps it
            assert r.status == 200
        # the explicit opt-out: any local process may open the page, as before
        assert opened.open_url == opened.url
        assert f"display: {opened.url}\n" in printed
        async with aiohttp.ClientSession() as fresh, fresh.get(opened.url + "/") as r:
            assert r.status == 200


async def test_a_page_that_can_release_an_estop_needs_the_token_too(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An e-stop's Release goes through the page and lets a robot move: a graph with an
    estop node and no web joystick served the page without a token, and any local process
    could scrape its session and release the stop."""
    g = GraphBuilder("stop")
    g.add("stop", "estop")
    g.add("view", "display", params={"port": 0})
    async with Runtime(g.build()) as rt, aiohttp.ClientSession() as http:
        view = rt.runner("view").executor.node  # type: ignore[attr-defined]
        printed = capsys.readouterr().out
        assert "needs its token: stop can drive from the page" in printed, printed
        async with http.get(view.url + "/") as r:
            assert r.status == 401
